"""Tests of the registration refinement and its residual-based covariance (tracking.uncertainty),
and of track()'s covariances against the exact truth of the synthetic room over noise draws."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from open3d_pnerf.camera import intrinsic_matrix
from open3d_pnerf.synthetic import DepthNoise, camera_path, room_scene, synthetic_sequence
from open3d_pnerf.tracking import OdometryOptions, consistency_of_errors, pose_errors, track
from open3d_pnerf.tracking.odometry import FrameRegistration
from open3d_pnerf.errors import InputError
from open3d_pnerf.tracking.uncertainty import DepthFrame, fit, misregistration_covariance, motion_rad, refine

SIMULATED = OdometryOptions().without_misregistration()  # a simulated sensor


@pytest.fixture(scope="module")
def room():
    """The synthetic room, its 320x240 intrinsic and an exact depth image of its first view."""
    scene = room_scene(0)
    intrinsic = synthetic_sequence(1, 320, 240, scene=scene).sequence.intrinsic
    return scene, intrinsic, scene.render(camera_path(scene, 300)[0], intrinsic)["depth"].astype(np.float64)


def block_noise(shape, sigma: float, block: int, seed: int) -> np.ndarray:
    """Noise (m) constant over block x block pixels, independent between blocks."""
    h, w = shape
    field = np.random.default_rng(seed).normal(0, sigma, (h // block + 1, w // block + 1))
    return np.kron(field, np.ones((block, block)))[:h, :w]


def twist(T: np.ndarray) -> np.ndarray:
    return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])


def test_refine_recovers_a_known_shift_and_fit_scores_it(room):
    _, intrinsic, depth = room
    K = intrinsic_matrix(intrinsic)
    source = DepthFrame.of(depth + block_noise(depth.shape, 0.002, 1, 0) * (depth > 0), K, 10.0)
    target = DepthFrame.of(depth, K, 10.0)
    truth = np.eye(4)
    start = np.eye(4)
    start[:3, 3] = [0.01, -0.005, 0.008]  # 1.4 cm off
    start[:3, :3] = Rotation.from_rotvec([0.004, 0.0, -0.003]).as_matrix()
    good = refine(source, target, start, 0.03)
    error = twist(good.transformation @ np.linalg.inv(truth))
    assert np.abs(error).max() < 1e-3  # < 1 mm / mrad from 1.4 cm / 5 mrad off (4,800 samples of 2 mm noise)
    assert error @ np.linalg.solve(good.covariance, error) < chi2.ppf(0.999, 6)  # and within its covariance
    bad = fit(source, target, start, 0.03)
    np.testing.assert_array_equal(bad.transformation, start)
    assert good.usable and good.overlap > 0.9
    assert 0.001 < good.residual_rms < 0.0025  # 2 mm of source noise, projected on the normals
    assert bad.residual_rms > 2 * good.residual_rms


def test_misregistration_floor_grows_with_the_square_of_the_motion(room):
    """The floor's rotation std is misregistration_rad + misregistration_per_squared_motion * m^2, m
    the motion: the rotation angle plus the translation over the depth; the residuals' part is the
    same whatever the floor."""
    _, intrinsic, depth = room
    K = intrinsic_matrix(intrinsic)
    frame = DepthFrame.of(depth, K, 10.0)
    turned = np.eye(4)
    turned[:3, :3] = Rotation.from_rotvec([0.0, 0.02, 0.0]).as_matrix()  # 20 mrad, no translation
    moved = np.eye(4)
    moved[:3, 3] = [0.0, 0.0, 0.05]
    assert motion_rad(turned, 2.0) == pytest.approx(0.02)
    assert motion_rad(moved, 2.0) == pytest.approx(0.025)
    a, k = 1.5e-3, 2.0
    without = fit(frame, frame, turned, 0.03)
    constant = fit(frame, frame, turned, 0.03, a)
    growing = fit(frame, frame, turned, 0.03, a, k)
    np.testing.assert_allclose(np.diag(constant.covariance - without.covariance)[:3], a**2)
    rad = a + k * 0.02**2  # 2.3 mrad
    np.testing.assert_allclose(np.diag(growing.covariance - without.covariance)[:3], rad**2)
    depth_ratio = np.diag(growing.covariance - without.covariance)[3:] / rad**2  # median depth^2
    assert np.ptp(depth_ratio) < 1e-9 and np.sqrt(depth_ratio[0]) == pytest.approx(growing.depth)
    np.testing.assert_array_equal(growing.residual_covariance, without.residual_covariance)
    np.testing.assert_allclose(growing.residual_covariance + misregistration_covariance(rad, growing.depth),
                               growing.covariance, rtol=1e-12, atol=0)
    # frames that did not move while they were taken (a loop closure of two still keyframes): the
    # constant floor alone, whatever the baseline between them; one moving 50 mm at 2 m: the square of
    # the two steps' mean
    still = fit(frame, frame, turned, 0.03, a, k, frame_steps=[np.eye(4), np.eye(4)])
    np.testing.assert_allclose(np.diag(still.covariance - without.covariance)[:3], a**2)
    one_moving = fit(frame, frame, turned, 0.03, a, k, frame_steps=[np.eye(4), moved])
    rad = a + k * (0.5 * 0.05 / one_moving.depth) ** 2
    np.testing.assert_allclose(np.diag(one_moving.covariance - without.covariance)[:3], rad**2)


@pytest.mark.parametrize("name", ["misregistration_rad", "misregistration_per_squared_motion",
                                  "misregistration_systematic"])
def test_a_negative_misregistration_is_refused(name):
    with pytest.raises(InputError, match=f"{name} must be >= 0"):
        OdometryOptions(**{name: -1e-3})


def test_covariance_holds_for_noise_correlated_over_blocks(room):
    """Sensor noise of 2 mm constant over 8x8-pixel blocks (several samples share each value): over
    12 noise draws the refined registrations' errors have a mean NEES per dof in the chi-square
    band of 72 degrees of freedom, so the covariance counts correlated pixels once (counting them
    as independent measurements, as Open3D's information matrix does, would make it several
    times too small)."""
    _, intrinsic, depth = room
    K = intrinsic_matrix(intrinsic)
    target = DepthFrame.of(depth, K, 10.0)
    nees = []
    for seed in range(12):
        source = DepthFrame.of(depth + block_noise(depth.shape, 0.002, 8, seed) * (depth > 0), K, 10.0)
        result = refine(source, target, np.eye(4), 0.03)
        error = twist(result.transformation)
        nees.append(error @ np.linalg.solve(result.covariance, error))
    low, high = chi2.ppf([0.005, 0.995], 72) / 72
    assert low < np.mean(nees) / 6 < high, np.round(nees, 2)


def monte_carlo(scene, draws: int, frames: int, scale: float, loops: bool) -> dict:
    errors, covariances = [], []
    for draw in range(draws):
        seq = synthetic_sequence(300, 320, 240, seed=200 + draw, scene=scene).sequence.select(range(frames))
        seq = seq if scale == 1 else seq.at_scale(scale)
        traj = track(seq, loop_closure=loops, progress=False, odometry=SIMULATED)
        assert traj.failed_frames == [] and traj.flagged_frames == []
        errors.append(pose_errors(traj.poses, seq.gt_poses)[1:])
        covariances.append(traj.covariances[1:])
    return consistency_of_errors(np.concatenate(errors), np.concatenate(covariances), independent=draws)


@pytest.mark.slow
@pytest.mark.parametrize("scale", [1.0, 0.5])
@pytest.mark.parametrize("loops", [True, False])
def test_tracked_covariances_hold_over_noise_draws(room, scale, loops):
    """A known trajectory (frames 0-9 of the room's 300-frame circle), 8 independent draws of the
    simulated sensor (draws the constants were not chosen on): the mean NEES per dof lies in the
    chi-square band of 8 draws at two processing resolutions, with and without loop closures, and
    the per-axis z-scores' standard deviation within 0.7-1.4 (the benchmark's 40 draws hold it to
    0.8-1.25; from 8 draws, whose 9 frames share their errors, it scatters by about +-10%)."""
    result = monte_carlo(room[0], 8, 10, scale, loops)
    low, high = result["nees_band"]
    assert low < result["nees_per_dof"] < high, result
    assert 0.7 < result["z_std"] < 1.4, result


def test_a_simulated_sensor_with_noise_is_refined_to_a_fraction_of_a_millimetre(room):
    """The registration error on two noisy simulated frames is far below the sensor noise: the
    sub-pixel refinement removes Open3D's pixel snapping."""
    scene, _, _ = room
    noise = dataclasses.replace(DepthNoise(), disparity_step=0.0)
    seq = synthetic_sequence(300, 320, 240, seed=7, scene=scene, noise=noise).sequence.select([0, 1])
    result = FrameRegistration(seq).register(0, 1, np.eye(4), SIMULATED)
    truth = np.linalg.inv(seq.gt_poses[1]) @ seq.gt_poses[0]
    error = twist(truth @ np.linalg.inv(result.transformation))
    assert np.linalg.norm(error[3:]) < 4e-4 and np.linalg.norm(error[:3]) < 4e-4, error
