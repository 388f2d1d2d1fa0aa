"""Initial guesses for a registration that do not come from a motion model, for frames that moved
too far for odometry to find from the last motion: the colour images' ORB keypoints matched and
solved by PnP-RANSAC on the source's depth (:func:`feature_registration`), and Open3D's global
registration of the two frames' point clouds (FPFH features + RANSAC, :func:`global_registration`).
"""

from __future__ import annotations

import cv2
import numpy as np
import open3d as o3d

from ..camera import unproject

ORB_KEYPOINTS = 1000
"""Keypoints ORB keeps per image for :func:`feature_registration`."""
MIN_FEATURE_INLIERS = 20
"""Fewer keypoint matches than this agreeing on one motion (within PNP_REPROJECTION_PX): no guess."""
PNP_REPROJECTION_PX = 3.0
"""A match agrees with a motion when the source point reprojects within this many pixels of its
match in the target image."""


def orb_keypoints(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ORB keypoints (OpenCV) of a (H, W) uint8 image: positions (N, 2) pixels and descriptors (N, 32) uint8."""
    keypoints, descriptors = cv2.ORB_create(nfeatures=ORB_KEYPOINTS).detectAndCompute(gray, None)
    if descriptors is None:
        return np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8)
    return np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2), descriptors


def feature_registration(source: tuple[np.ndarray, np.ndarray], source_depth: np.ndarray,
                         target: tuple[np.ndarray, np.ndarray], K: np.ndarray) -> np.ndarray | None:
    """(4, 4) transformation mapping source-camera points into the target camera, from keypoints
    (positions (N, 2) px, ORB descriptors) of the two images: matches that pass Lowe's ratio test
    (0.8), lifted to 3D by the source's depth (H, W, m, 0 = none) and intrinsic K (3, 3), then
    PnP-RANSAC (OpenCV's, deterministic: its random generator has a fixed seed) on their target
    positions and a Levenberg-Marquardt polish on the inliers. None when fewer than
    MIN_FEATURE_INLIERS matches agree."""
    (uv_s, des_s), (uv_t, des_t) = source, target
    if len(uv_s) < MIN_FEATURE_INLIERS or len(uv_t) < MIN_FEATURE_INLIERS:
        return None
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(des_s, des_t, k=2)
    good = np.array([(m[0].queryIdx, m[0].trainIdx) for m in pairs
                     if len(m) == 2 and m[0].distance < 0.8 * m[1].distance], int).reshape(-1, 2)
    pixels = np.round(uv_s[good[:, 0]]).astype(int)
    z = source_depth[pixels[:, 1].clip(0, source_depth.shape[0] - 1), pixels[:, 0].clip(0, source_depth.shape[1] - 1)]
    good, z = good[z > 0], z[z > 0]
    if len(good) < MIN_FEATURE_INLIERS:
        return None
    points = unproject(np.asarray(K, np.float64), *uv_s[good[:, 0]].astype(np.float64).T, z.astype(np.float64))
    seen = np.ascontiguousarray(uv_t[good[:, 1]], np.float64)
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(points, seen, K, None, iterationsCount=1000,
                                                 reprojectionError=PNP_REPROJECTION_PX, confidence=0.999,
                                                 flags=cv2.SOLVEPNP_EPNP)
    if not ok or inliers is None or len(inliers) < MIN_FEATURE_INLIERS:
        return None
    inliers = inliers[:, 0]
    rvec, tvec = cv2.solvePnPRefineLM(points[inliers], seen[inliers], K, None, rvec, tvec)
    transformation = np.eye(4)
    transformation[:3, :3], transformation[:3, 3] = cv2.Rodrigues(rvec)[0], tvec[:, 0]
    return transformation


def global_registration(source: np.ndarray, target: np.ndarray) -> np.ndarray | None:
    """(4, 4) transformation mapping source points (M, 3) onto target points, from FPFH features
    matched with RANSAC and refined by point-to-plane ICP (Open3D's global registration, as its
    reconstruction system uses between fragments), or None when fewer than 30% of the source
    voxels end up within two voxels of the target. The voxel is a fortieth of the median depth
    (4 cm at 1.6 m). Seeded: the same frames give the same answer."""
    if len(source) < 100 or len(target) < 100:
        return None
    reg = o3d.pipelines.registration
    voxel = max(0.01, float(np.median(np.concatenate([source[:, 2], target[:, 2]]))) / 40)
    clouds, features = [], []
    for points in (source, target):
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(voxel)
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        clouds.append(cloud)
        features.append(reg.compute_fpfh_feature(cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel,
                                                                                             max_nn=100)))
    o3d.utility.random.seed(0)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        coarse = reg.registration_ransac_based_on_feature_matching(
            clouds[0], clouds[1], features[0], features[1], True, 1.5 * voxel,
            reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
            reg.RANSACConvergenceCriteria(100_000, 0.999))
        refined = reg.registration_icp(clouds[0], clouds[1], 2 * voxel, coarse.transformation,
                                       reg.TransformationEstimationPointToPlane())
    if refined.fitness < 0.3:
        return None
    return np.asarray(refined.transformation, np.float64)
