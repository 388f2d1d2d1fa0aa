"""A reconstruction's folder on disk: written atomically, read back with every file checked.

The folder holds ``reconstruction.json`` (format version, config, scene box, depth range,
intrinsic, frame split, timestamps, depth-error law, statistics), ``model.pt`` (the field's
weights only), ``poses.npy``, ``covariances.npy``, ``color_gains.npy``, ``observed.npy`` (the centres of the
voxels the training frames' depth saw, when there was depth), ``observed_depths.npy`` (the
nearest surface each training view saw around each pixel), ``mesh.ply`` (with
per-vertex ``depth_sigma`` and ``quality``), ``point_cloud.ply`` (per-point, the same), ``frames/``
(the frames it was built from, as an Open3D folder: what extending the map replays), and the
trajectory as ``trajectory_tum.txt``, ``trajectory.log`` and Open3D's ``trajectory.json`` (a
PinholeCameraTrajectory with the training intrinsic). Reading never unpickles code
(``torch.load(weights_only=True)``, ``np.load(allow_pickle=False)``).
"""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import torch

from ._files import atomic_write_all, read_json_object
from .camera import check_intrinsic, intrinsic_matrix, pinhole
from .config import ReconstructionConfig
from .data.open3d_folder import read_open3d_folder, write_sequence
from .data.trajectories import write_log_trajectory, write_open3d_trajectory, write_tum_trajectory
from .error_law import DepthErrorLaw
from .errors import CheckpointError, ConfigError, DatasetError, InputError
from .export import Geometry, read_mesh_ply, read_point_cloud_ply, write_mesh_ply, write_point_cloud_ply
from .fields import NDCWarp, block_boxes, block_tables
from .model import build_model
from .observed import ObservedSurface
from .training import safe_torch_load

FORMAT_VERSION = 2
FRAMES = "frames"
FRAMES_DEPTH_SCALE = 5000.0  # raw units per metre of the saved depth PNGs: 0.2 mm steps up to 13 m
META_KEYS = ("format_version", "config", "aabb", "depth_range", "intrinsic", "train_indices", "holdout_indices",
             "timestamps", "depth_error")


def write_folder(recon, directory, frames: bool = True) -> Path:
    """Write `recon` (a Reconstruction) into `directory`: every file goes to a temporary first and
    all are renamed at the end, so a failure or Ctrl-C while saving leaves the folder's previous
    files intact; a mesh or point cloud with nothing in it is not written (and a stale one removed).
    frames: write recon.frames (when it has them) as ``frames/``; False leaves them out (and a
    stale ``frames/`` removed): the folder then cannot be extended."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    staged = _stage_frames(recon.frames, d) if frames and recon.frames is not None else None
    intr, law, model = recon.intrinsic, recon.depth_error, recon.model
    meta = {
        "format_version": FORMAT_VERSION,
        "config": recon.config.to_dict(),
        "aabb": recon.aabb.tolist(),
        "depth_range": None if model.depth_range is None else model.depth_range.tolist(),
        "intrinsic": {"width": intr.width, "height": intr.height, "K": intrinsic_matrix(intr).tolist()},
        "train_indices": recon.train_indices.tolist(),
        "holdout_indices": recon.holdout_indices.tolist(),
        "timestamps": recon.timestamps.tolist(),
        "depth_error": law.to_dict(),
        "stats": recon.stats,
        "observed_voxel_size": None if recon.observed is None else recon.observed.voxel_size,
        "blocks": block_boxes(model.field),
        "block_tables": block_tables(model.field),
        "ndc": None if model.field.warp is None else model.field.warp.to_dict(),
    }
    weights = {k: v.cpu() for k, v in model.field.state_dict().items()}
    writes = {
        d / "model.pt": lambda p: torch.save(weights, p),
        d / "reconstruction.json": lambda p: Path(p).write_text(json.dumps(meta, indent=1)),
        d / "poses.npy": lambda p: np.save(p, recon.poses),
        d / "covariances.npy": lambda p: np.save(p, recon.covariances),
        d / "color_gains.npy": lambda p: np.save(p, recon.color_gains),
        d / "trajectory_tum.txt": lambda p: write_tum_trajectory(p, recon.poses, recon.timestamps),
        d / "trajectory.log": lambda p: write_log_trajectory(p, recon.poses),
        d / "trajectory.json": lambda p: write_open3d_trajectory(p, recon.poses, recon.intrinsic),
    }
    if recon.observed is not None:
        writes[d / "observed.npy"] = lambda p: np.save(p, recon.observed.centres)
        if recon.observed.depths is not None:
            writes[d / "observed_depths.npy"] = lambda p: np.save(p, recon.observed.depths)
    geometry, empty = recon.geometry or Geometry(), []
    for name, shape, write in (
        ("mesh.ply", geometry.mesh, lambda p: write_mesh_ply(p, geometry.mesh, geometry.mesh_sigma)),
        ("point_cloud.ply", geometry.point_cloud,
         lambda p: write_point_cloud_ply(p, geometry.point_cloud, geometry.point_sigma)),
    ):
        if shape is not None and not shape.is_empty():
            writes[d / name] = write
        else:
            empty.append(name)
    atomic_write_all(writes)
    _swap_in(staged, d / FRAMES)
    if recon.observed is None:
        (d / "observed.npy").unlink(missing_ok=True)
    if recon.observed is None or recon.observed.depths is None:
        (d / "observed_depths.npy").unlink(missing_ok=True)
    for name in empty:
        (d / name).unlink(missing_ok=True)  # never leave a stale file from an earlier run
        warnings.warn(f"{name} not written: the model has no confident surface yet (train longer)")
    return d


def _stage_frames(frames, d: Path) -> Path:
    """Write the frames to a new folder beside ``d/frames`` (to be swapped in by :func:`_swap_in`)."""
    staged = d / f"{FRAMES}.partial"
    shutil.rmtree(staged, ignore_errors=True)
    write_sequence(frames, staged, FRAMES_DEPTH_SCALE)
    return staged


def _swap_in(staged: Path | None, target: Path) -> None:
    """Put the staged frames folder in place of `target` (removed when nothing is staged)."""
    old = target.with_name(f"{FRAMES}.old")
    shutil.rmtree(old, ignore_errors=True)
    if target.exists():
        target.rename(old)
    if staged is not None:
        staged.rename(target)
    shutil.rmtree(old, ignore_errors=True)


def read_folder(directory, device: str | None = None) -> dict:
    """The parts of a reconstruction saved by :func:`write_folder`, checked, as Reconstruction's
    keyword arguments; CheckpointError names the file and what is wrong with it."""
    d = Path(directory)
    meta_path = d / "reconstruction.json"
    meta = _read_meta(meta_path)
    try:
        config = ReconstructionConfig.from_dict(meta["config"])
        if "n_coarse_render" not in meta["config"].get("sampling", {}):
            # written when renders sampled as training does: keep rendering so (its depth law was fitted to those)
            config = config.replace(**{"sampling.n_coarse_render": config.sampling.n_coarse})
        if device:
            config = config.replace(device=device)
    except (ConfigError, TypeError, ValueError) as exc:
        raise CheckpointError(f"{meta_path}: incompatible config ({exc})") from None
    try:
        aabb = np.asarray(meta["aabb"], np.float32).reshape(2, 3)
        if not (np.isfinite(aabb).all() and (aabb[0] < aabb[1]).all()):
            raise ValueError(f"aabb {meta['aabb']} is not a finite [min, max] box")
        K = np.asarray(meta["intrinsic"]["K"], np.float64).reshape(3, 3)
        intrinsic = check_intrinsic(pinhole(meta["intrinsic"]["width"], meta["intrinsic"]["height"],
                                            K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
        timestamps = np.asarray(meta["timestamps"], np.float64).reshape(-1)
        n = len(timestamps)
        train, holdout = (np.asarray(meta[k], int).reshape(-1) for k in ("train_indices", "holdout_indices"))
        if any(((i < 0) | (i >= n)).any() for i in (train, holdout)):
            raise ValueError(f"frame indices outside [0, {n})")
        depth_range = _depth_range(meta["depth_range"])
        law = _error_law(meta["depth_error"])
        blocks = meta.get("blocks")
        if blocks is not None:
            blocks = np.asarray(blocks, np.float32).reshape(-1, 2, 3)
            if not (np.isfinite(blocks).all() and (blocks[:, 0] < blocks[:, 1]).all()
                    and np.allclose(blocks[-1], aabb)):
                raise ValueError("blocks are not finite [min, max] boxes ending with aabb")
        tables = meta.get("block_tables")
        if blocks is not None and tables is None and config.field == "hashgrid":
            tables = [config.hashgrid.log2_table_size] * len(blocks)  # written before blocks were sized
        if tables is not None and (blocks is None or config.field != "hashgrid" or len(tables) != len(blocks)
                                   or not all(isinstance(t, int) and 4 <= t <= 26 for t in tables)):
            raise ValueError(f"block_tables {tables!r} are not one log2 table size in [4, 26] per block of a "
                             "grown hash grid")
        warp = meta.get("ndc")
        if warp is not None:
            warp = NDCWarp.from_dict(warp)
        voxel = meta.get("observed_voxel_size")
        if voxel is not None and not (isinstance(voxel, (int, float)) and np.isfinite(voxel) and voxel > 0):
            raise ValueError(f"observed_voxel_size {voxel!r} is not a size > 0 (m)")
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f"{meta_path}: malformed metadata ({exc})") from None
    try:
        model = build_model(config, aabb, depth_range=depth_range, blocks=blocks, tables=tables, warp=warp)
    except ConfigError as exc:
        raise CheckpointError(f"{meta_path}: {exc}") from None
    try:
        model.field.load_state_dict(safe_torch_load(d / "model.pt"))
    except (RuntimeError, KeyError, TypeError) as exc:
        raise CheckpointError(f"{d / 'model.pt'}: weights do not match the config ({exc})") from None
    mesh, mesh_sigma = _read_ply(d / "mesh.ply", read_mesh_ply) or (None, None)
    cloud, point_sigma = _read_ply(d / "point_cloud.ply", read_point_cloud_ply) or (None, None)
    gains = _load_array(d / "color_gains.npy", (n, 3))
    if not (gains > 0).all():
        raise CheckpointError(f"{d / 'color_gains.npy'}: colour gains must be > 0")
    poses, observed = _load_array(d / "poses.npy", (n, 4, 4)), None
    if voxel is not None:
        depths = None  # the training views' depth, in folders that have it: seen through
        if (d / "observed_depths.npy").is_file():
            depths = _load_array(d / "observed_depths.npy", (len(train), intrinsic.height, intrinsic.width))
        observed = ObservedSurface(float(voxel), _load_array(d / "observed.npy", (None, 3)), depths,
                                   intrinsic_matrix(intrinsic), poses[train])
    return dict(frames=_read_frames(d / FRAMES, n, intrinsic.width, intrinsic.height, config.image_scale),
                model=model, config=config, poses=poses,
                covariances=_load_array(d / "covariances.npy", (n, 6, 6)), intrinsic=intrinsic, train_indices=train,
                holdout_indices=holdout, timestamps=timestamps, color_gains=gains, depth_error=law, observed=observed,
                geometry=Geometry(mesh, mesh_sigma, cloud, point_sigma), stats=meta.get("stats") or {})


def _read_frames(path: Path, n: int, width: int, height: int, image_scale: float):
    """The saved frames (an RGBDSequence of n frames read lazily), or None without ``frames/``."""
    if not path.is_dir():
        return None
    try:
        frames = read_open3d_folder(path)
    except (DatasetError, InputError) as exc:
        raise CheckpointError(f"{path}: unreadable saved frames ({exc})") from None
    trained = frames.at_scale(image_scale).image_size
    if len(frames) != n or abs(trained[0] - height) > 1 or abs(trained[1] - width) > 1:
        raise CheckpointError(f"{path}: {len(frames)} frames of {frames.image_size[1]}x{frames.image_size[0]}, "
                              f"expected {n} that train at {width}x{height}")
    return frames


def _read_meta(path: Path) -> dict:
    """The JSON object of a saved reconstruction, checked for its format version and keys."""
    if not path.is_file():
        raise CheckpointError(f"{path.parent}: not a saved reconstruction (reconstruction.json missing)")
    meta = read_json_object(path, CheckpointError)
    if meta.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"{path}: format version {meta.get('format_version')!r}, this library reads "
                              f"{FORMAT_VERSION} (a folder from an unreleased development version: reconstruct again)")
    missing = [k for k in META_KEYS if k not in meta]
    if missing or not isinstance(meta["config"], dict):
        raise CheckpointError(f"{path}: incomplete, missing {missing or ['config (an object)']}")
    return meta


def _load_array(path: Path, shape: tuple) -> np.ndarray:
    """A finite .npy array of the given shape, None for any size on an axis (never unpickled)."""
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise CheckpointError(f"{path}: missing or corrupt ({exc})") from None
    if len(arr.shape) != len(shape) or any(n not in (None, m) for n, m in zip(shape, arr.shape)) \
            or not np.isfinite(arr).all():
        raise CheckpointError(f"{path}: expected finite values of shape {shape}, got shape {arr.shape}")
    return arr


def _read_ply(path: Path, read):
    """read(path), or None without the file; a saved PLY that reads as empty is corrupt."""
    if not path.is_file():
        return None
    out = read(path)
    if out[0].is_empty():
        raise CheckpointError(f"{path}: unreadable or empty PLY (a save never writes an empty one)")
    return out


def _depth_range(value) -> np.ndarray | None:
    """A saved depth_range: None, or finite [near, far] with 0 < near < far (ValueError otherwise)."""
    if value is None:
        return None
    rng = np.asarray(value, np.float64) if isinstance(value, list) else np.full(2, np.nan)
    if rng.shape != (2,) or not (np.isfinite(rng).all() and 0 < rng[0] < rng[1]):
        raise ValueError(f"depth_range {value!r} is not [near, far], 0 < near < far")
    return rng


def _error_law(value) -> DepthErrorLaw:
    """A saved depth_error: {scale > 0, floor >= 0, dof > 0 or null (a Gaussian)} and, from folders
    that have them, unseen >= 0, unseen_ramp > 0, edge >= 0 and through >= 0 (the defaults
    otherwise; ValueError if wrong)."""
    keys = {"scale", "floor", "dof"}
    if not isinstance(value, dict) or not keys <= set(value) <= keys | {"unseen", "unseen_ramp", "edge", "through"}:
        raise ValueError(f"depth_error {value!r} is not {{scale, floor, dof[, unseen, unseen_ramp, edge, through]}}")
    number = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)  # noqa: E731
    scale, floor, dof = value["scale"], value["floor"], value["dof"]
    unseen, ramp, edge, through = (value.get(k, getattr(DepthErrorLaw, k))
                                   for k in ("unseen", "unseen_ramp", "edge", "through"))
    if not (number(scale) and scale > 0 and number(floor) and floor >= 0 and (dof is None or number(dof) and dof > 0)
            and number(unseen) and unseen >= 0 and number(ramp) and ramp > 0 and number(edge) and edge >= 0
            and number(through) and through >= 0):
        raise ValueError(f"depth_error {value!r}: need scale > 0, floor >= 0, dof > 0 or null, unseen >= 0, "
                         "unseen_ramp > 0, edge >= 0 and through >= 0")
    return DepthErrorLaw(float(scale), float(floor), np.inf if dof is None else float(dof), float(unseen), float(ramp),
                         float(edge), float(through))
