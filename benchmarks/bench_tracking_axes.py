"""Which axes of the tracked poses their covariances miss: per axis of the pose error (rotation
about x, y, z and translation along them, in the camera frame, as `pose_errors` gives it), the RMS
error, the median standard deviation the covariances claim and the z-scores' RMS, and the NEES per
dof of the rotation and translation blocks alone, on TUM fr1/xyz and 7-Scenes 150-199 at 640x480
and 320x240, loop closures on and off. A diagnostic of the NEES rows of `results/tracking.md`
(the same tracker and sequences, one run each). And how the rotation errors grow: their
correlation with each frame's turn from frame 0 (its rotation angle: what a registration error
common to every step, a calibration error, grows with; OdometryOptions.misregistration_systematic)
and with the square root of the frame's index (what independent step errors grow with), and the
least-squares slope of the error against that turn (mrad per rad).

Then the same for the steps (loop closures off): each accepted odometry edge's error against the
ground truth's step (a left perturbation in the target camera's frame, as the edge's covariance
is), and how its rotation and translation errors go together: the correlation and slope (m) of the
translation along x against the rotation about y, and along y against x (a turn about a point at
depth d in front of the camera moves it by (-d ry, d rx, 0)), beside the frames' median depth.
And the ground truth's time offset seen by a second tracker: Open3D's point-to-plane ICP (depth
alone, 1 cm voxels) between consecutive frames of TUM fr1/xyz's report half (16-31; the offset was
chosen with this tracker on 0-15), the RMS of its steps' rotation errors against the ground truth
read at each offset. About a minute; needs the shared data.

    python benchmarks/bench_tracking_axes.py

Writes benchmarks/results/tracking_axes.json and tracking_axes.md.
"""

from __future__ import annotations

import time
import warnings

import numpy as np
import open3d as o3d
from bench_suite import machine, write_result
from bench_tracking import OFFSET_GRID, REAL, real_sequence, tracked

from open3d_pnerf.camera import rotation_vector
from open3d_pnerf.data import load_sequence
from open3d_pnerf.tracking import consistency_of_errors, pose_errors

AXES = ("rx", "ry", "rz", "tx", "ty", "tz")


def block_nees(errors: np.ndarray, covariances: np.ndarray, block: slice) -> float:
    """Mean NEES per dof of one (3-dof) block of errors (M, 6) under the marginal covariances (M, 6, 6)."""
    e, c = errors[:, block], covariances[:, block, block]
    return float(np.einsum("ni,ni->n", e, np.linalg.solve(c, e[..., None])[..., 0]).mean() / 3)


def axes_of(errors: np.ndarray, covariances: np.ndarray) -> dict:
    """Per-axis RMS error and median claimed sigma (mrad / mm), z-score RMS (1 for honest error bars; a std
    would hide an error common to the frames); block and whole NEES per dof."""
    sigma = np.sqrt(np.diagonal(covariances, axis1=1, axis2=2))
    z = errors / sigma
    return {"rms_error": dict(zip(AXES, np.round(1000 * np.sqrt((errors**2).mean(0)), 2).tolist())),
            "median_sigma": dict(zip(AXES, np.round(1000 * np.median(sigma, 0), 2).tolist())),
            "z_rms": dict(zip(AXES, np.round(np.sqrt((z**2).mean(0)), 2).tolist())),
            "nees_per_dof_rotation": round(block_nees(errors, covariances, slice(0, 3)), 3),
            "nees_per_dof_translation": round(block_nees(errors, covariances, slice(3, 6)), 3),
            "nees_per_dof": round(consistency_of_errors(errors, covariances)["nees_per_dof"], 3)}


def growth(errors: np.ndarray, gt: np.ndarray) -> dict:
    """How the rotation error norms of frames 1.. (errors (M, 6)) grow: correlation with the ground
    truth's turn from frame 0 (rad) and with sqrt(frame index), and the slope against that turn
    (mrad per rad)."""
    turned = np.linalg.norm(rotation_vector(np.linalg.inv(gt[0])[:3, :3] @ gt[1:, :3, :3]), axis=1)
    size = np.linalg.norm(errors[:, :3], axis=1)
    return {"corr(turn)": round(float(np.corrcoef(turned, size)[0, 1]), 2),
            "corr(sqrt steps)": round(float(np.corrcoef(np.sqrt(np.arange(1, len(size) + 1)), size)[0, 1]), 2),
            "slope (mrad/rad)": round(float(1000 * turned @ size / (turned @ turned)), 1)}


def step_error(gt: np.ndarray, s: int, t: int, transformation) -> np.ndarray:
    """(6,) error [rotation, translation] of a step (4, 4, frame s's camera -> frame t's) against the
    ground truth's (gt: (N, 4, 4) poses), exp(xi) T = T_gt (first order)."""
    delta = np.linalg.inv(gt[t]) @ gt[s] @ np.linalg.inv(np.asarray(transformation))
    return np.concatenate([rotation_vector(delta[:3, :3]), delta[:3, 3]])


def odometry_steps(traj) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    """The pose graph's odometry edges (loop closures are its uncertain ones) as (source, target,
    transformation (4, 4), information (6, 6))."""
    return [(e.source_node_id, e.target_node_id, np.asarray(e.transformation), np.asarray(e.information))
            for e in traj.pose_graph.edges if not e.uncertain]


def step_errors(traj, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Errors (M, 6) of the graph's odometry edges against the ground truth's steps (step_error), and
    the edges' covariances (M, 6, 6)."""
    steps = odometry_steps(traj)
    return (np.array([step_error(gt, s, t, T) for s, t, T, _ in steps]),
            np.array([np.linalg.inv(information) for *_, information in steps]))


def rotation_rms_by_offset(steps, frames) -> dict:
    """RMS rotation error (mrad) of `steps` ((source, target, transformation, ...) between frames of
    TUM fr1/xyz `frames`) against its ground truth read at each offset (s) of OFFSET_GRID, by offset."""
    out = {}
    for offset in OFFSET_GRID:
        gt = load_sequence(REAL["tum_fr1_xyz"], gt_time_offset=float(offset)).select(frames).gt_poses
        rotations = np.array([step_error(gt, s, t, T)[:3] for s, t, T, *_ in steps])
        out[f"{offset + 0:g}"] = round(float(1000 * np.sqrt((rotations**2).sum(1).mean())), 2)
    return out


def coupling(errors: np.ndarray) -> dict:
    """Correlation and least-squares slope (m) of tx against ry and of ty against rx."""
    out = {}
    for t, r in (("tx", 1), ("ty", 0)):
        x, y = errors[:, r], errors[:, 3 + "xyz".index(t[1])]
        out[f"corr({AXES[r]},{t})"] = round(float(np.corrcoef(x, y)[0, 1]), 2)
        out[f"slope {t}/{AXES[r]} (m)"] = round(float(x @ y / (x @ x)), 2)
    return out


def icp_time_offset(frames=range(16, 32)) -> dict:
    """RMS rotation error (mrad) of Open3D point-to-plane ICP's consecutive-frame steps on TUM
    fr1/xyz `frames` against the ground truth read at each offset (s) of OFFSET_GRID."""
    seq = load_sequence(REAL["tum_fr1_xyz"]).select(frames)
    clouds = []
    for i in range(len(seq)):
        cloud = o3d.geometry.PointCloud.create_from_depth_image(o3d.geometry.Image(seq[i].depth), seq.intrinsic,
                                                                depth_scale=1.0).voxel_down_sample(0.01)
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.05, max_nn=30))
        clouds.append(cloud)
    steps = [(i, i + 1, o3d.pipelines.registration.registration_icp(
        a, b, 0.05, np.eye(4), o3d.pipelines.registration.TransformationEstimationPointToPlane(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=50)).transformation)
        for i, (a, b) in enumerate(zip(clouds, clouds[1:]))]
    return rotation_rms_by_offset(steps, frames)


def run() -> dict:
    out, steps = {}, {}
    for name in REAL:
        for scale in (1.0, 0.5):
            seq = real_sequence(name).at_scale(scale)
            for loops in (True, False):
                traj, _, _ = tracked(seq, loops)
                errors = pose_errors(traj.poses, seq.gt_poses)[1:]
                key = f"{name} {seq.intrinsic.width}x{seq.intrinsic.height} {'loops' if loops else 'odometry only'}"
                out[key] = {**axes_of(errors, traj.covariances[1:]), "growth": growth(errors, seq.gt_poses)}
                print(key, out[key], flush=True)
                if not loops:
                    e, c = step_errors(traj, seq.gt_poses)
                    depth = np.median(np.concatenate([seq[i].depth[seq[i].depth > 0] for i in range(0, len(seq), 5)]))
                    steps[key] = {**axes_of(e, c), **coupling(e), "median depth (m)": round(float(depth), 2)}
                    print(key, "steps", steps[key], flush=True)
    return out, steps


def markdown(report: dict) -> str:
    lines = [f"# Per-axis pose errors against their covariances ({report['minutes']} min, "
             "`python benchmarks/bench_tracking_axes.py`)", "", f"{report['machine']}.", "",
             "Per axis (camera frame; rotation in mrad, translation in mm): RMS error / median claimed sigma "
             "/ z-score RMS. Then the NEES per dof of the rotation block, the translation block and the whole.", "",
             "| sequence, setting | " + " | ".join(AXES) + " | NEES/dof rotation, translation, whole |",
             "| --- |" + " --- |" * (len(AXES) + 1)]
    lines += [f"| {key} | " + " | ".join(cells(r)) + " |" for key, r in report["runs"].items()]
    lines += ["", "## How the rotation errors grow", "",
              "The rotation error's norm per frame: its correlation with the turn from frame 0 (rotation angle; a "
              "registration error common to every step grows with it) and with the square root of the frame's index "
              "(independent step errors), and its slope against that turn (mrad per rad).",
              "", "| sequence, setting | corr with turn | corr with sqrt(steps) | slope mrad/rad |",
              "| --- | --- | --- | --- |"]
    lines += [f"| {key} | {r['growth']['corr(turn)']} | {r['growth']['corr(sqrt steps)']} | "
              f"{r['growth']['slope (mrad/rad)']} |" for key, r in report["runs"].items() if "growth" in r]
    lines += ["", "## Steps: the odometry edges against the ground truth's steps (loop closures off)", "",
              "Per axis as above, the NEES per dof of the rotation block, the translation block and the whole, then "
              "how the errors couple: correlation / slope (m) of tx against ry and of ty against rx, and the "
              "frames' median depth (m).", "",
              "| sequence, setting | " + " | ".join(AXES) + " | NEES/dof | tx against ry | ty against rx | depth |",
              "| --- |" + " --- |" * (len(AXES) + 4)]
    lines += [f"| {key} | " + " | ".join(cells(r)) + f" | {r['corr(ry,tx)']} / {r['slope tx/ry (m)']} | "
              f"{r['corr(rx,ty)']} / {r['slope ty/rx (m)']} | {r['median depth (m)']} |"
              for key, r in report["steps"].items()]
    icp = report["icp_time_offset"]
    lines += ["", "## The ground truth's time offset by a second tracker: Open3D point-to-plane ICP, TUM fr1/xyz 16-31",
              "", "RMS rotation error (mrad) of its consecutive-frame steps against the ground truth read that many "
              "seconds off (this file's other tables read it at bench_tracking.GT_TIME_OFFSET).", "",
              "| offset s | " + " | ".join(icp) + " |", "|" + " --- |" * (len(icp) + 1),
              "| step rotation RMS mrad | " + " | ".join(str(v) for v in icp.values()) + " |"]
    return "\n".join(lines) + "\n"


def cells(r: dict) -> list[str]:
    """A row's cells: per axis RMS error / median sigma / z RMS, then the blocks' and the whole NEES."""
    return ([f"{r['rms_error'][a]} / {r['median_sigma'][a]} / {r['z_rms'][a]}" for a in AXES]
            + [f"{r['nees_per_dof_rotation']}, {r['nees_per_dof_translation']}, {r['nees_per_dof']}"])


def main() -> None:
    warnings.simplefilter("ignore")  # the tracker's flagged-frame warnings: the table says more
    start = time.perf_counter()
    runs, steps = run()
    report = {"machine": machine(), "runs": runs, "steps": steps, "icp_time_offset": icp_time_offset()}
    report["minutes"] = round((time.perf_counter() - start) / 60, 1)
    write_result("tracking_axes", report, markdown(report))


if __name__ == "__main__":
    main()
