"""A synthetic indoor scene with an exact ground-truth mesh, rendered to noisy RGB-D.

The scene is a room (floor, walls, ceiling) with a table, boxes, spheres and a cylinder,
each with a procedural solid texture. Frames are ray cast with Open3D's RaycastingScene
along a camera path inside the room, then corrupted by a Kinect-like depth noise model
(:class:`DepthNoise`). Everything is deterministic from the seed, and frames are rendered
lazily when indexed, so a 2,000-frame sequence costs no memory until it is read.

World frame: z up, metres; cameras are camera-to-world with OpenCV axes (like the rest of
the library).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d

from .camera import backproject, check_intrinsic, check_poses, intrinsic_matrix
from .data.sequence import RGBDSequence
from .errors import InputError
from .raycast import pinhole_rays
from .targets.noise import SensorNoise


@dataclasses.dataclass(frozen=True)
class DepthNoise:
    """A structured-light depth sensor's errors (defaults: a Kinect v1 / Xtion).

    sensor: the random axial noise sigma_z(z) (:class:`~open3d_pnerf.targets.SensorNoise`, the
    model the depth targets assume; its systematic part is not simulated);
    disparity_step: focal * baseline / subpixel (m px); depth is quantised in disparity, so
    the step grows as z^2 / disparity_step (0 = no quantisation); grazing_cos: pixels whose
    surface is seen at |cos(angle)| below this are missing; edge_jump: pixels next to a
    depth jump larger than this fraction of z are missing with probability edge_dropout;
    dropout: random missing pixels; range_m: (near, far) measurable depth.
    """

    sensor: SensorNoise = SensorNoise()
    disparity_step: float = 525 * 0.075 * 8
    grazing_cos: float = 0.15
    edge_jump: float = 0.04
    edge_dropout: float = 0.5
    dropout: float = 0.01
    range_m: tuple[float, float] = (0.4, 5.0)

    @classmethod
    def none(cls) -> "DepthNoise":
        """Exact depth (still zero outside range_m)."""
        return cls(sensor=SensorNoise(a=0.0, b=0.0), disparity_step=0.0, grazing_cos=0.0, edge_dropout=0.0, dropout=0.0)

    def sigma(self, z: np.ndarray) -> np.ndarray:
        """Axial noise std (m) at z-depth z (m)."""
        return self.sensor.sigma(np.asarray(z))

    def apply(self, depth: np.ndarray, cos_incidence: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Noisy copy of an exact z-depth map (H, W) m; 0 marks missing pixels."""
        hit = depth > 0
        z = depth + rng.standard_normal(depth.shape) * self.sigma(depth)
        if self.disparity_step > 0:
            disparity = np.round(self.disparity_step / np.where(hit, z, 1.0))
            z = self.disparity_step / np.maximum(disparity, 1.0)
        missing = ~hit | (np.abs(cos_incidence) < self.grazing_cos) | (rng.random(depth.shape) < self.dropout)
        if self.edge_dropout > 0:
            missing |= _near_depth_jump(depth, self.edge_jump) & (rng.random(depth.shape) < self.edge_dropout)
        missing |= (z < self.range_m[0]) | (z > self.range_m[1])
        return np.where(missing, 0.0, z).astype(np.float32)


def _near_depth_jump(depth: np.ndarray, jump: float) -> np.ndarray:
    """Pixels whose 4-neighbourhood has a depth change above `jump` * z (or a miss)."""
    padded = np.pad(depth, 1, mode="edge")
    near = np.zeros(depth.shape, bool)
    h, w = depth.shape
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        near |= np.abs(padded[dy:dy + h, dx:dx + w] - depth) > jump * np.maximum(depth, 1e-6)
    return near


@dataclasses.dataclass
class SyntheticScene:
    """Triangle meshes with procedural textures; ``mesh`` is the exact ground truth.

    albedo[k] = (base RGB in [0, 1] (3,), texture frequencies (4, 3) cycles/m, phases (4,))
    for the geometry with id k of the ray-casting scene.
    """

    parts: list[o3d.geometry.TriangleMesh]
    albedo: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
    room_size: tuple[float, float, float]

    def __post_init__(self):
        self._scene = o3d.t.geometry.RaycastingScene()
        for part in self.parts:
            self._scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(part))

    @property
    def mesh(self) -> o3d.geometry.TriangleMesh:
        """The ground-truth surface as one legacy triangle mesh (world metres)."""
        mesh = o3d.geometry.TriangleMesh()
        for part in self.parts:
            mesh += part
        return mesh

    def render(self, pose: np.ndarray, intrinsic: o3d.camera.PinholeCameraIntrinsic) -> dict:
        """Exact render from a camera-to-world pose (4, 4).

        Returns color (H, W, 3) float32 in [0, 1], depth (H, W) float32 z-depth m (0 where
        no surface), cos_incidence (H, W) |cos| between ray and surface normal.
        """
        intrinsic = check_intrinsic(intrinsic)
        rays = pinhole_rays(pose, intrinsic_matrix(intrinsic), intrinsic.width, intrinsic.height)
        hits = self._scene.cast_rays(rays)
        rays = rays.numpy()
        depth = hits["t_hit"].numpy()  # directions have unit camera-z: t = z-depth
        hit = np.isfinite(depth)
        depth = np.where(hit, depth, 0.0).astype(np.float32)
        points = rays[..., :3] + rays[..., 3:] * depth[..., None]
        normals = hits["primitive_normals"].numpy()
        view = rays[..., 3:] / np.linalg.norm(rays[..., 3:], axis=-1, keepdims=True)
        cos = np.abs((normals * view).sum(-1))
        ids = hits["geometry_ids"].numpy()[hit].astype(np.int64)
        base, freqs, phases = (np.stack(a)[ids] for a in zip(*self.albedo))  # per hit pixel
        pattern = np.sin((freqs * points[hit][:, None]).sum(-1) * 2 * np.pi + phases).mean(-1)
        shade = 0.6 + 0.4 * np.abs(normals[hit] @ np.array([0.3, 0.5, 0.81]))  # a fixed distant light
        color = np.zeros(depth.shape + (3,), np.float32)
        color[hit] = np.clip(base * ((0.6 + 0.4 * pattern) * shade)[:, None], 0, 1)  # solid texture
        return {"color": color, "depth": depth, "cos_incidence": cos.astype(np.float32)}

    def visible_points(self, poses: np.ndarray, intrinsic: o3d.camera.PinholeCameraIntrinsic,
                       voxel_size: float = 0.01) -> o3d.geometry.PointCloud:
        """The ground-truth surface seen by the cameras `poses` (N, 4, 4): exact hit points,
        one per `voxel_size` voxel (a hit point, not a voxel average, so every point lies on
        the surface). The reference for completeness (unseen surfaces do not count)."""
        K = intrinsic_matrix(intrinsic)
        kept, keys = np.zeros((0, 3)), np.zeros(0, np.int64)
        for pose in check_poses(poses):
            depth = self.render(pose, intrinsic)["depth"]
            pts = backproject(depth, K, pose)[0]
            cell = np.floor(pts / voxel_size).astype(np.int64) + (1 << 20)  # voxel index >= 0 (to 10 km at 1 cm)
            new_keys = (cell[:, 0] << 42) | (cell[:, 1] << 21) | cell[:, 2]
            keys, first = np.unique(np.concatenate([keys, new_keys]), return_index=True)  # first hit per voxel
            kept = np.concatenate([kept, pts])[first]
        return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(kept))


def room_scene(seed: int = 0, room_size: tuple[float, float, float] = (4.0, 5.0, 2.6)) -> SyntheticScene:
    """An indoor room centred on the origin (floor at z = 0): walls, floor, ceiling, a table
    with legs, boxes, spheres and a cylinder. `seed` jitters placement, colours, textures."""
    rng = np.random.default_rng(seed)
    sx, sy, sz = room_size
    parts, albedo = [], []

    def add(mesh: o3d.geometry.TriangleMesh, base, scale_cycles: float = 3.0):
        mesh.compute_triangle_normals()
        parts.append(mesh)
        freqs = rng.normal(size=(4, 3)) * scale_cycles * np.array([1.0, 1.0, 1.0])
        albedo.append((np.asarray(base, float), freqs, rng.uniform(0, 2 * np.pi, 4)))

    def box(size, centre, base, cycles=3.0):
        mesh = o3d.geometry.TriangleMesh.create_box(*size)
        mesh.translate(np.asarray(centre, float) - np.asarray(size, float) / 2)
        add(mesh, base, cycles)

    jitter = lambda s: rng.uniform(-s, s, 2)  # noqa: E731
    box((sx, sy, sz), (0, 0, sz / 2), (0.85, 0.80, 0.70), 2.0)  # the room: seen from inside
    tx, ty = jitter(0.3)
    box((1.4, 0.8, 0.05), (tx, ty, 0.75), (0.55, 0.35, 0.2), 6.0)  # table top
    for lx in (-0.62, 0.62):
        for ly in (-0.32, 0.32):
            box((0.06, 0.06, 0.72), (tx + lx, ty + ly, 0.36), (0.3, 0.2, 0.1), 8.0)
    for (cx, cy), size in (((-1.2, 1.6), (0.6, 0.5, 0.9)), ((1.3, -1.5), (0.8, 0.6, 0.45)),
                           ((1.4, 1.7), (0.4, 0.4, 1.3))):
        jx, jy = jitter(0.15)
        box(size, (cx + jx, cy + jy, size[2] / 2), rng.uniform(0.2, 0.9, 3), 5.0)
    for centre, radius in (((tx + 0.3, ty, 0.775 + 0.15), 0.15), ((-1.2, -1.4, 0.3), 0.3)):
        sphere = o3d.geometry.TriangleMesh.create_sphere(radius, resolution=24)
        sphere.translate(centre)
        add(sphere, rng.uniform(0.2, 0.9, 3), 8.0)
    cylinder = o3d.geometry.TriangleMesh.create_cylinder(0.12, 0.3, resolution=24)
    cylinder.translate((tx - 0.35, ty + 0.1, 0.775 + 0.15))
    add(cylinder, rng.uniform(0.2, 0.9, 3), 8.0)
    return SyntheticScene(parts, albedo, room_size)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world (4, 4), OpenCV axes (x right, y down, z forward), at `eye` facing `target`."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    x = np.cross(z, up)
    if not np.linalg.norm(x) > 1e-9 * np.linalg.norm(z) > 0:  # also catches NaN
        raise InputError(f"look_at: the view direction {target - eye} is zero or parallel to up={up}; pass another up")
    z /= np.linalg.norm(z)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    pose[:3, 3] = eye
    return pose


def camera_path(scene: SyntheticScene, n_frames: int, arc_deg: float = 360.0) -> np.ndarray:
    """(n_frames, 4, 4) poses on an ellipse inside the room at ~1.4 m height, looking at the
    room's centre at table height with a slow sideways sweep."""
    sx, sy, _ = scene.room_size
    a = np.deg2rad(arc_deg) * np.arange(n_frames) / max(n_frames, 1)
    eyes = np.stack([0.3 * sx * np.cos(a), 0.3 * sy * np.sin(a), 1.4 + 0.15 * np.sin(3 * a)], 1)
    targets = np.stack([0.4 * np.sin(2 * a), 0.4 * np.cos(2 * a), 0.7 + 0.1 * np.cos(a)], 1)
    return np.stack([look_at(e, t) for e, t in zip(eyes, targets)])


@dataclasses.dataclass
class SyntheticData:
    """A rendered synthetic sequence with its ground truth.

    sequence.gt_poses are the exact poses; poses (N, 4, 4) are what a user would get from a
    tracker (exact poses plus `pose_noise`), covariances (N, 6, 6) their covariance
    ([rotation rad, translation m], right perturbation, like track()).
    """

    sequence: RGBDSequence
    scene: SyntheticScene
    poses: np.ndarray
    covariances: np.ndarray

    @property
    def mesh(self) -> o3d.geometry.TriangleMesh:
        return self.scene.mesh

    def reference_points(self, voxel_size: float = 0.01, stride: int = 4) -> o3d.geometry.PointCloud:
        """Exact surface seen by every `stride`-th frame (at the sequence's resolution)."""
        gt = self.sequence.gt_poses
        return self.scene.visible_points(gt[::stride], self.sequence.intrinsic, voxel_size)


def synthetic_sequence(n_frames: int = 40, width: int = 320, height: int = 240, seed: int = 0,
                       noise: DepthNoise | None = None, pose_noise: tuple[float, float] = (0.0, 0.0),
                       color_noise: float = 0.01, scene: SyntheticScene | None = None) -> SyntheticData:
    """Render the room scene along a full circle of `n_frames` camera poses.

    width, height: image size (px), focal length 0.82 * width (a Kinect's 58 deg field of
    view); noise: depth noise model (default DepthNoise()); pose_noise: (rotation std rad,
    translation std m) added to each returned pose (the sequence's gt_poses stay exact);
    color_noise: std of Gaussian colour noise in [0, 1] units. Frames render lazily and
    identically every time they are read.
    """
    if n_frames < 1 or width < 8 or height < 8:
        raise InputError(f"synthetic_sequence needs n_frames >= 1 and images >= 8x8, got {n_frames}, {width}x{height}")
    if np.shape(pose_noise) != (2,) or not (np.min(pose_noise) >= 0 and np.isfinite(pose_noise).all()):
        raise InputError(f"pose_noise must be (rotation std rad, translation std m) >= 0, got {pose_noise}")
    noise = DepthNoise() if noise is None else noise
    scene = scene or room_scene(seed)
    focal = 0.82 * width
    intrinsic = o3d.camera.PinholeCameraIntrinsic(width, height, focal, focal, (width - 1) / 2, (height - 1) / 2)
    gt = camera_path(scene, n_frames)

    def reader(i: int):
        def read():
            rng = np.random.default_rng([seed, i])
            out = scene.render(gt[i], intrinsic)
            color = out["color"] + rng.standard_normal(out["color"].shape) * color_noise
            depth = noise.apply(out["depth"], out["cos_incidence"], rng)
            return (np.clip(color, 0, 1) * 255 + 0.5).astype(np.uint8), depth

        return read

    rot_std, trans_std = pose_noise
    rng = np.random.default_rng([seed, 1_000_003])
    poses = gt.copy()
    for pose in poses:
        rotvec = rng.standard_normal(3) * rot_std
        pose[:3, :3] = pose[:3, :3] @ o3d.geometry.get_rotation_matrix_from_axis_angle(rotvec)
        pose[:3, 3] += pose[:3, :3] @ (rng.standard_normal(3) * trans_std)
    covariance = np.diag([rot_std**2] * 3 + [trans_std**2] * 3)
    sequence = RGBDSequence([reader(i) for i in range(n_frames)], intrinsic,
                            timestamps=np.arange(n_frames) / 30.0, gt_poses=gt, name=f"synthetic room (seed {seed})")
    return SyntheticData(sequence, scene, poses, np.repeat(covariance[None], n_frames, 0))
