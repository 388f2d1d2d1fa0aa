"""Pose refinement: the twist parametrisation, the covariance prior, and a short run on the
synthetic room with noisy poses that moves them toward the truth."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

import open3d_pnerf as pn
from open3d_pnerf.config import ReconstructionConfig
from open3d_pnerf.errors import ConfigError
from open3d_pnerf.pose_refinement import PoseCorrections, follow_refinement
from open3d_pnerf.synthetic import synthetic_sequence


def covs(*stds) -> np.ndarray:
    """(N, 6, 6) diagonal covariances, one std (rad and m alike) per frame."""
    return np.stack([np.eye(6) * s**2 for s in stds])


def test_zero_twists_leave_poses_unchanged():
    pc = PoseCorrections(covs(0.01, 0.01))
    poses = torch.as_tensor(np.stack([np.eye(4), np.eye(4)]), dtype=torch.float32)
    poses[1, :3, 3] = torch.tensor([1.0, 2.0, 3.0])
    out = pc(poses, torch.tensor([0, 1]))
    torch.testing.assert_close(out, poses)


def test_a_twist_is_applied_on_the_right_in_the_camera_frame():
    """T exp(xi): a pure translation twist moves the camera along its own axes."""
    pc = PoseCorrections(covs(0.1))
    angle = 0.3
    with torch.no_grad():
        pc.twists[0] = torch.tensor([0.0, 0.0, angle, 0.5, 0.0, 0.0])  # rotate about camera z, move along camera x
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("y", 90, degrees=True).as_matrix()  # camera x points to world -z
    T[:3, 3] = [1.0, 0.0, 0.0]
    refined = pc.corrected(T[None])[0]
    expected_rot = T[:3, :3] @ Rotation.from_rotvec([0, 0, angle]).as_matrix()
    np.testing.assert_allclose(refined[:3, :3], expected_rot, atol=1e-6)
    # exp of [w, v] with w along z and v along x: the translation is V(w) v
    w = np.array([0, 0, angle])
    theta = angle
    W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    V = np.eye(3) + (1 - np.cos(theta)) / theta**2 * W + (theta - np.sin(theta)) / theta**3 * W @ W
    np.testing.assert_allclose(refined[:3, 3], T[:3, 3] + T[:3, :3] @ V @ [0.5, 0, 0], atol=1e-6)


def test_prior_is_half_the_mahalanobis_energy_and_fixed_frames_stay():
    pc = PoseCorrections(np.stack([np.diag([1e-4, 1e-4, 1e-4, 4e-4, 4e-4, 4e-4]), np.zeros((6, 6))]))
    with torch.no_grad():
        pc.twists[0] = torch.tensor([0.0, 0.01, 0.0, 0.0, 0.0, 0.04])  # 1 sigma and 2 sigma
        pc.twists[1] = torch.tensor([0.5, 0.0, 0.0, 0.0, 0.0, 0.0])  # a fixed frame: ignored
    assert pc.prior().item() == pytest.approx(0.5 * (1 + 4), rel=1e-5)  # the mean over the one free frame
    out = pc(torch.eye(4).expand(2, 4, 4), torch.tensor([0, 1]))
    torch.testing.assert_close(out[1], torch.eye(4))  # zero covariance: the pose is held fixed
    pc.prior().backward()
    assert pc.twists.grad[1].abs().sum() == 0 and pc.twists.grad[0, 5] > 0


def test_bad_pose_refinement_settings_raise_config_error():
    for field, value in (("refine_poses", 1), ("optimizer.pose_lr", 0.0), ("objective.pose_prior_weight", -1.0)):
        with pytest.raises(ConfigError, match=field):
            ReconstructionConfig.preset("test", **{field: value})


@pytest.mark.slow
def test_refinement_moves_noisy_poses_toward_the_truth():
    """Synthetic room, 2 cm / 0.6 degree pose noise: a short run reduces the trajectory error
    (after the rigid alignment that removes the gauge freedom shared by field and poses)."""
    data = synthetic_sequence(12, 160, 120, seed=0, pose_noise=(0.01, 0.02))
    cfg = ReconstructionConfig.preset("test", field="grid", max_steps=300, holdout_every=0, progress=False,
                                      refine_poses=True, **{"export.calibrate_depth_sigma": False})
    recon = pn.reconstruct(data.sequence, cfg, poses=data.poses, covariances=data.covariances)
    gt = data.sequence.gt_poses
    before = pn.absolute_trajectory_error(data.poses, gt)["rmse"]
    after = pn.absolute_trajectory_error(recon.poses, gt)["rmse"]
    assert after < 0.85 * before, (before, after)  # measured here: 31.7 -> 25.4 mm


def test_unrefined_frames_follow_a_rigid_shift_of_the_refined_ones():
    rng = np.random.default_rng(0)
    original = np.stack([np.eye(4)] * 6)
    original[:, :3, :3] = Rotation.random(6, random_state=1).as_matrix()
    original[:, :3, 3] = rng.normal(size=(6, 3)) * [1.0, 0.01, 0.01]  # a short, nearly straight path
    shift = np.eye(4)
    shift[:3, :3] = Rotation.from_rotvec([0.02, -0.01, 0.03]).as_matrix()
    shift[:3, 3] = [0.05, -0.02, 0.01]
    other = np.eye(4)
    other[:3, 3] = [0.3, 0.2, 0.1]
    moved = follow_refinement(original, shift @ original, other[None])[0]
    np.testing.assert_allclose(moved, shift @ other, atol=1e-9)


def test_pose_corrections_resume_from_a_checkpoint_like_a_straight_run(tmp_path):
    """The twists and their Adam state are in the checkpoint: 4 + 4 steps equal 8 steps."""
    from open3d_pnerf.batches import RayBatcher
    from open3d_pnerf.data import load_sample
    from open3d_pnerf.model import build_model
    from open3d_pnerf.scene import scene_box
    from open3d_pnerf.targets import depth_targets
    from open3d_pnerf.training import Trainer

    seq = load_sample().at_scale(0.5)
    targets = depth_targets(seq, poses=seq.gt_poses, progress=False)
    aabb = scene_box(targets, seq.gt_poses, seq.K)
    cfg = ReconstructionConfig.preset("test", max_steps=8, progress=False, refine_poses=True)
    noise = covs(*[0.01] * len(seq))

    def trainer(checkpoint_dir=None):
        torch.manual_seed(0)
        model = build_model(cfg, aabb, seq.gt_poses, seq.K, noise)
        return Trainer(model, RayBatcher(seq, targets, "cpu", cfg.seed), cfg, None, checkpoint_dir)

    straight = trainer()
    straight.train()
    first = trainer(tmp_path)
    real_step = first.train_step

    def step_until_ctrl_c():  # Ctrl-C before step 5: the trainer checkpoints after step 4
        if first.step == 4:
            raise KeyboardInterrupt
        return real_step()

    first.train_step = step_until_ctrl_c
    assert first.train()["interrupted"]
    second = trainer(tmp_path)
    second.load_checkpoint(tmp_path / "checkpoint.pt")
    assert second.step == 4 and second.model.pose_corrections.twists.abs().sum() > 0
    second.train()
    torch.testing.assert_close(second.model.pose_corrections.twists, straight.model.pose_corrections.twists, rtol=1e-5, atol=1e-7)
