"""Verified RGB-D odometry between two frames of a sequence (Open3D tensor pipeline).

``o3d.t.pipelines.odometry.rgbd_odometry_multi_scale`` (hybrid photometric + geometric
loss) estimates the transformation X that maps source-camera points into the target
camera (``p_target = X @ p_source``, so ``X ~ inv(pose_target) @ pose_source`` for
camera-to-world poses). Open3D reports
convergence but not whether the answer is right, so every result is checked: enough valid
depth, a finite transformation, enough geometric overlap after alignment, and a plausible
correction of the initial guess; and it carries its geometric residual and the covariance
estimated from it (:mod:`open3d_pnerf.tracking.uncertainty`), which the tracker compares with
the sequence's other registrations. :class:`FrameRegistration` also offers the initial guesses of
:mod:`~open3d_pnerf.tracking.starts`, for frames that moved too far for odometry.
"""

from __future__ import annotations

import dataclasses
import functools
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor

import cv2
import numpy as np
import open3d as o3d

from ..camera import motion
from ..data.sequence import RGBDSequence
from ..errors import InputError
from .starts import feature_registration, global_registration, orb_keypoints
from .uncertainty import DepthFrame, refine

odometry = o3d.t.pipelines.odometry
ODOMETRY_HALF_FROM = 320
"""Images at least this many pixels wide are registered by Open3D at half resolution (its cost is
mostly the finest level's; the refinement then aligns the full images to a fraction of a pixel)."""
_METHODS = {
    "hybrid": odometry.Method.Hybrid,
    "point_to_plane": odometry.Method.PointToPlane,
    "intensity": odometry.Method.Intensity,
}


@dataclasses.dataclass(frozen=True)
class OdometryOptions:
    """Settings of the pairwise RGB-D odometry and of its failure checks."""

    method: str = "hybrid"
    """Open3D odometry loss: "hybrid" (photometric + depth), "point_to_plane" or "intensity"."""
    iterations: tuple[int, ...] = (20, 10, 5)
    """Open3D's Gauss-Newton iterations per pyramid level, coarsest level first (the most)."""
    inlier_distance_m: float = 0.03
    """A source point whose aligned 3D position lies within this distance of the target's
    point at the same pixel is a correspondence (overlap test and refinement)."""
    min_overlap: float = 0.5
    """Minimum fraction of the source's valid depth pixels that must find a correspondence."""
    min_valid_depth: float = 0.05
    """Minimum fraction of pixels with valid depth (in (0, max_depth)) in both frames."""
    max_translation_m: float = 0.3
    """Largest plausible change of translation relative to the initial guess (m)."""
    max_rotation_deg: float = 30.0
    """Largest plausible change of rotation relative to the initial guess (degrees)."""
    residual_ratio: float = 2.5
    """A registration whose point-to-plane residual RMS exceeds this many times the median of the
    sequence's accepted registrations so far is suspicious: the tracker tries other initial
    guesses and keeps the best fit (a wrong pose of a textured scene leaves residuals many times
    those of the right ones)."""
    overlap_ratio: float = 0.8
    """A registration whose overlap is below this fraction of the median overlap of the sequence's
    accepted registrations so far is doubtful: the tracker tries the other initial guesses too (a
    wrong minimum of a textured scene overlaps less than the right one, with a residual that need
    not stand out)."""

    search_all_above_m: float = 0.05
    """When the predicted motion from the last frame exceeds this (m) or search_all_above_deg, or
    a registration lands that far from the prediction, the tracker tries every initial guess
    (including the keypoint and global registrations) and keeps the best fit, even if the first
    passes: at such motions odometry can settle in a wrong minimum with an unremarkable residual."""
    search_all_above_deg: float = 5.0
    """See search_all_above_m (degrees)."""

    misregistration_rad: float = 1e-3
    """How far (rad; translation: this angle times the median depth) a real sensor's registration
    of two frames stays off beyond what its residuals show when the camera has not moved between
    them: calibration, lens distortion. Added to every registration's covariance; 0 for a
    simulated sensor."""
    misregistration_per_squared_motion: float = 0.25
    """What the misregistration grows by per squared radian of the camera's motion while it takes
    the two frames (m: each frame's step from its neighbour, rotation angle plus translation over
    the median depth, averaged over the two; for consecutive frames, their registration's own
    motion): k m^2 rad. Motion blur, rolling shutter and wrong minima leave a registration off
    more than in proportion to how far the camera moved: TUM fr1/xyz's small steps fit best
    without a term linear in m, 7-Scenes every 10th frame's 68 mm / 3.7 degree steps leave frames
    wrong beyond their covariance without one (benchmarks/results/tracking_tuning.md). 0 for a
    simulated sensor."""
    misregistration_systematic: float = 0.04
    """What every pose's misregistration grows by per radian the camera turned from the reference
    frame (rotation std; translation: that std times the median depth), common to all the
    sequence's registrations (a calibration error: registrations that all turn a few percent too
    far or about a tilted axis): it grows with the turn, not with the number of steps, and loop
    closures, measured with the same error, cannot shrink it. Added to the pose covariances after
    the pose graph's (see track). 0 for a simulated sensor."""

    def without_misregistration(self) -> "OdometryOptions":
        """These options for a simulated sensor: no calibration, timing or rolling-shutter error."""
        return dataclasses.replace(self, misregistration_rad=0.0, misregistration_per_squared_motion=0.0,
                                   misregistration_systematic=0.0)

    def criteria(self) -> list:
        """Open3D convergence criteria, one per pyramid level."""
        return [odometry.OdometryConvergenceCriteria(int(i)) for i in self.iterations]

    def __post_init__(self):
        if self.method not in _METHODS:
            raise InputError(f"method must be one of {sorted(_METHODS)}, got {self.method!r}")
        if not self.iterations or any(int(i) < 1 for i in self.iterations):
            raise InputError(f"iterations must be positive integers per level, got {self.iterations!r}")
        for name in ("inlier_distance_m", "max_translation_m", "max_rotation_deg", "residual_ratio", "overlap_ratio",
                     "search_all_above_m", "search_all_above_deg"):
            if not getattr(self, name) > 0:
                raise InputError(f"{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("misregistration_rad", "misregistration_per_squared_motion", "misregistration_systematic"):
            if not getattr(self, name) >= 0:
                raise InputError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if not 0 <= self.min_overlap <= 1:
            raise InputError(f"min_overlap must be in [0, 1], got {self.min_overlap!r}")
        if not 0 < self.min_valid_depth <= 1:
            raise InputError(f"min_valid_depth must be in (0, 1], got {self.min_valid_depth!r}")


@dataclasses.dataclass(frozen=True)
class PairResult:
    """Outcome of registering a source frame to a target frame."""

    transformation: np.ndarray
    """(4, 4) float64, maps source-camera points into the target camera (metres)."""
    fitness: float
    """Open3D's fraction of all pixels that were odometry inliers at the finest level."""
    inlier_rmse: float
    """Open3D's ``inlier_rmse`` of the odometry loss at the finest pyramid level."""
    overlap: float
    """Fraction of the source's valid depth pixels with a correspondence after alignment."""
    success: bool
    message: str = ""
    """Why the registration was rejected ("" when it succeeded)."""
    residual_rms: float = np.inf
    """RMS point-to-plane residual of the correspondences after alignment (m)."""
    inliers: int = 0
    """Source pixels with a correspondence after alignment (of the refinement's samples)."""
    covariance: np.ndarray = dataclasses.field(default_factory=lambda: np.full((6, 6), np.inf))
    """(6, 6) covariance of the transformation from its residuals, with the misregistration floor
    (uncertainty.fit)."""
    residual_covariance: np.ndarray = dataclasses.field(default_factory=lambda: np.full((6, 6), np.inf))
    """(6, 6) the part of `covariance` the residuals show, without the floor."""
    depth: float = np.nan
    """Median depth of the refinement's inlier correspondences (m)."""
    init: str = ""
    """Which initial guess the registration started from."""
    odometry_transformation: np.ndarray | None = None
    """(4, 4) Open3D's odometry answer before the point-to-plane refinement: with the hybrid loss,
    the relative pose that fits the colour images (its intensity term dominates), which
    tracking.color measures the colour cameras by (None when Open3D failed)."""


class FrameRegistration:
    """Registers frames of one sequence to each other, caching recently used images.

    sequence: the RGB-D sequence. max_depth: depth beyond this (m) is ignored. device: an
    ``o3d.core.Device`` or string such as "CPU:0" / "CUDA:0" (None = CPU:0). cache_size: how
    many frames' images are kept (see :meth:`reserve`). Frames announced by :meth:`prefetch`
    are read and prepared on a background thread while the caller registers others.
    """

    def __init__(self, sequence: RGBDSequence, max_depth: float = 3.0, device=None, cache_size: int = 4):
        if not max_depth > 0:
            raise InputError(f"max_depth must be > 0 metres, got {max_depth!r}")
        self.sequence = sequence
        self.max_depth = float(max_depth)
        self.device = _device(device)
        self.K = sequence.K
        self.odometry_scale = 0.5 if sequence.image_size[1] >= ODOMETRY_HALF_FROM else 1.0
        self.intrinsic = o3d.core.Tensor(np.diag([self.odometry_scale] * 2 + [1.0]) @ self.K)
        self._cache: OrderedDict[int, _Image | Future] = OrderedDict()
        self._wanted: set[int] = set()  # frames to prefetch after the next odometry
        self.cache_size = cache_size

    def image(self, index: int) -> "_Image":
        """Frame `index`: an Open3D tensor RGBD image for the odometry (at half resolution from
        ODOMETRY_HALF_FROM pixels wide: :meth:`register` finishes every registration on the full
        depth images), its valid-depth fraction, and its full-resolution geometry for the refinement."""
        self._wanted.discard(index)
        if index not in self._cache:
            self._store(index, self._load(index))
        self._cache.move_to_end(index)
        image = self._cache[index]
        if isinstance(image, Future):  # prefetched: wait for it (its errors are raised here)
            image = self._cache[index] = image.result()
        return image

    def prefetch(self, index: int) -> None:
        """Have frame `index` read and prepared on the background thread while the caller registers
        others (nothing when it is cached or beyond the sequence). The reading starts when the
        next registration's Open3D odometry, which uses every core, has finished."""
        if 0 <= index < len(self.sequence) and index not in self._cache:
            self._wanted.add(index)

    def _start_prefetching(self) -> None:
        for index in sorted(self._wanted):
            self._store(index, _reader().submit(self._load, index))
        self._wanted.clear()

    def reserve(self, frames: list[int]) -> None:
        """Let the cache hold the images of `frames` (loop closures revisit the keyframes pair by
        pair: each is then read once), as many as FRAME_CACHE_MB holds of images the size of the
        first one's."""
        if frames:
            fit = int(FRAME_CACHE_MB * 2**20 // self.image(frames[0]).nbytes)
            self.cache_size = max(self.cache_size, min(len(frames), fit))

    def _store(self, index: int, image) -> None:
        self._cache[index] = image
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)

    def _load(self, index: int) -> "_Image":
        frame = self.sequence[index]
        color = np.ascontiguousarray(self.sequence.color_on_depth_grid(frame.color, frame.depth))
        gray = cv2.cvtColor(color, cv2.COLOR_RGB2GRAY)
        depth = frame.depth
        valid = float(np.mean((depth > 0) & (depth < self.max_depth)))
        geometry = DepthFrame.of(depth, self.K, self.max_depth)
        if self.odometry_scale < 1:  # every other pixel (the colour blurred first), centres at even pixels
            color, depth = cv2.pyrDown(color), np.ascontiguousarray(depth[::2, ::2])
        rgbd = o3d.t.geometry.RGBDImage(
            o3d.t.geometry.Image(o3d.core.Tensor(color)), o3d.t.geometry.Image(o3d.core.Tensor(depth))
        ).to(self.device)
        return _Image(rgbd, valid, geometry, gray)

    def forget(self, index: int) -> None:
        """Drop frame `index`'s cached image (a frame that was taken back and may come again)."""
        self._cache.pop(index, None)
        self._wanted.discard(index)

    def register(
        self,
        source: int,
        target: int,
        init: np.ndarray | None = None,
        options: OdometryOptions = OdometryOptions(),
        init_name: str = "",
        prior: np.ndarray | None = None,
        frame_steps: list[np.ndarray] | None = None,
    ) -> PairResult:
        """Align frame `source` to frame `target`, starting from `init` (4x4, source->target).

        prior: the expected transformation (4x4) that the plausible-motion limits are measured
        from (default: `init`), so that a guess from elsewhere (a global registration) is held
        to the same motion limits as the motion model. frame_steps: the frames' own steps (each a
        (4, 4) relative pose from its neighbour frame), what the misregistration floor grows with
        (uncertainty.refine); None: the registration's own motion, the frames' step when they are
        consecutive and a bound (the whole baseline) when they are not.
        Never raises for bad data: a failed registration comes back with success=False,
        the initial guess as its transformation and the reason in ``message``.
        """
        init = np.eye(4) if init is None else np.asarray(init, dtype=np.float64)
        src, tgt = self.image(source), self.image(target)
        failed = dict(transformation=init, success=False, init=init_name)
        for which, image in (("source", src), ("target", tgt)):
            if image.valid < options.min_valid_depth:
                return PairResult(
                    **failed, fitness=0.0, inlier_rmse=np.inf, overlap=0.0,
                    message=f"too few valid depth pixels in the {which} frame "
                    f"({image.valid:.1%} < {options.min_valid_depth:.0%})",
                )
        try:
            result = odometry.rgbd_odometry_multi_scale(
                src.rgbd, tgt.rgbd, self.intrinsic, o3d.core.Tensor(init), depth_scale=1.0,
                depth_max=self.max_depth, criteria_list=options.criteria(), method=_METHODS[options.method],
            )
            found = result.transformation.numpy().astype(np.float64)
            if not np.isfinite(found).all():
                raise RuntimeError("non-finite transformation")
        except RuntimeError as exc:  # Open3D raises on singular systems and empty images
            return PairResult(
                **failed, fitness=0.0, inlier_rmse=np.inf, overlap=0.0,
                message=f"Open3D odometry failed ({str(exc).strip()})",
            )
        finally:
            self._start_prefetching()
        quality = refine(src.geometry, tgt.geometry, found, options.inlier_distance_m, options.misregistration_rad,
                         options.misregistration_per_squared_motion, frame_steps=frame_steps)
        transformation = quality.transformation
        moved_m, turned_deg = motion(np.linalg.inv(init if prior is None else prior) @ transformation)
        message = ""
        if not quality.usable:
            message = f"only {quality.inliers} correspondences after alignment"
        elif quality.overlap < options.min_overlap:
            message = f"overlap {quality.overlap:.2f} < min_overlap {options.min_overlap}"
        elif moved_m > options.max_translation_m or turned_deg > options.max_rotation_deg:
            message = (
                f"implausible motion {moved_m:.3f} m / {turned_deg:.1f} deg from the expected one "
                f"(limits {options.max_translation_m} m / {options.max_rotation_deg} deg)"
            )
        return PairResult(
            transformation=transformation if not message else init,
            fitness=float(result.fitness),
            inlier_rmse=float(result.inlier_rmse),
            overlap=quality.overlap,
            success=not message,
            message=message,
            residual_rms=quality.residual_rms,
            inliers=quality.inliers,
            covariance=quality.covariance,
            residual_covariance=quality.residual_covariance,
            depth=quality.depth,
            init=init_name,
            odometry_transformation=found,
        )

    def global_guess(self, source: int, target: int) -> np.ndarray | None:
        """An initial guess (4, 4, source -> target) from :func:`global_registration` of the two
        frames' point clouds, or None when it finds no consistent match."""
        src, tgt = self.image(source), self.image(target)
        return global_registration(_cloud(src), _cloud(tgt))

    def feature_guess(self, source: int, target: int) -> np.ndarray | None:
        """An initial guess (4, 4, source -> target) from :func:`feature_registration` of the two
        frames' colour keypoints, or None when too few of them agree on one motion."""
        src, tgt = self.image(source), self.image(target)
        return feature_registration(src.keypoints, src.geometry.depth, tgt.keypoints, self.K)


@dataclasses.dataclass
class _Image:
    rgbd: o3d.t.geometry.RGBDImage
    valid: float
    geometry: DepthFrame
    gray: np.ndarray
    """(H, W) uint8: the colour image on the depth grid at full resolution, for its keypoints."""

    @functools.cached_property
    def keypoints(self) -> tuple[np.ndarray, np.ndarray]:
        """ORB keypoints of the colour image (computed when first asked): pixel positions (N, 2)
        and binary descriptors (N, 32) uint8."""
        return orb_keypoints(self.gray)

    @property
    def nbytes(self) -> int:
        """Memory (bytes) of the arrays it holds: the geometry's (those computed so far), the grey
        image and the RGBD image (not the keypoints, about 40 KB once computed)."""
        arrays = ([a for a in vars(self.geometry).values() if isinstance(a, np.ndarray)] + list(self.geometry.samples)
                  + [self.gray])
        tensors = (self.rgbd.color.as_tensor(), self.rgbd.depth.as_tensor())
        return sum(a.nbytes for a in arrays) + sum(t.num_elements() * t.dtype.byte_size() for t in tensors)


FRAME_CACHE_MB = 512
"""At most this much memory (MB) holds cached frame images when the cache is enlarged (reserve):
27 frames at 640x480, 107 at 320x240 (63-65 bytes per pixel)."""


@functools.lru_cache(maxsize=1)
def _reader() -> ThreadPoolExecutor:
    """The one background thread that reads and prepares prefetched frames (OpenCV's decoding and
    NumPy's array work release the GIL, so it runs beside the registration)."""
    return ThreadPoolExecutor(max_workers=1, thread_name_prefix="open3d_pnerf-frames")


def _cloud(image: _Image) -> np.ndarray:
    return image.geometry.points[image.geometry.depth > 0]


def _device(device) -> o3d.core.Device:
    if device is None:
        return o3d.core.Device("CPU:0")
    if isinstance(device, o3d.core.Device):
        return device
    if isinstance(device, str):
        try:
            return o3d.core.Device(device)
        except RuntimeError:
            raise InputError(f"device must look like 'CPU:0' or 'CUDA:0', got {device!r}") from None
    raise InputError(f"device must be None, a string or an o3d.core.Device, got {type(device).__name__}")
