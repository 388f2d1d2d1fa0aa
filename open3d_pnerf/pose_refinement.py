"""Pose refinement: a rigid correction of each training pose, optimised jointly with the
field and held near the tracked pose by a Gaussian prior from the pose covariance.

Convention (as :mod:`open3d_pnerf.tracking.covariance`): a camera-to-world pose T is
perturbed on the right, ``T exp(xi)``, with the twist ``xi = [rotation (rad), translation
(m)]`` in the camera's own frame, and the pose covariance Sigma (6, 6) is that of xi. The
prior is the Mahalanobis energy ``0.5 xi^T Sigma^-1 xi``: uncertain poses move freely,
certain ones stay.
"""

from __future__ import annotations

import numpy as np
import torch
from kornia.geometry.liegroup import Se3

from .tracking.metrics import rigid_alignment

# Poses whose covariance has a standard deviation below this (rad or m) in every direction
# (e.g. ground-truth poses given with zero covariance) are held fixed.
FIXED_STD = 1e-6


class PoseCorrections(torch.nn.Module):
    """Per-frame twists (N, 6), zero at the start, and their prior.

    covariances: (N, 6, 6) pose covariances of the N training frames ([rotation, translation]
    order, rad^2 / m^2). Frames whose covariance is (near) zero keep their pose.
    """

    def __init__(self, covariances: np.ndarray, device="cpu"):
        super().__init__()
        cov = np.asarray(covariances, dtype=np.float64)
        std = np.sqrt(np.clip(np.diagonal(cov, axis1=1, axis2=2), 0, None))
        free = (std > FIXED_STD).any(axis=1)
        safe = np.where(free[:, None, None], cov + 1e-12 * np.eye(6), np.eye(6))
        self.twists = torch.nn.Parameter(torch.zeros(len(cov), 6, device=device))
        self.register_buffer("information", torch.as_tensor(np.linalg.inv(safe), dtype=torch.float32, device=device))
        self.register_buffer("free", torch.as_tensor(free, device=device))

    def forward(self, poses: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
        """Corrected poses (R, 4, 4) = poses (R, 4, 4) @ exp(twist of frames (R,))."""
        xi = self.twists[frames] * self.free[frames, None]
        delta = Se3.exp(torch.cat([xi[:, 3:], xi[:, :3]], dim=1)).matrix()  # kornia: [translation, rotation]
        return poses @ delta

    def prior(self) -> torch.Tensor:
        """Mean over the free frames of 0.5 xi^T Sigma^-1 xi (dimensionless)."""
        xi = self.twists[self.free]
        if len(xi) == 0:
            return self.twists.sum() * 0.0
        return 0.5 * torch.einsum("ni,nij,nj->n", xi, self.information[self.free], xi).mean()

    def corrected(self, poses: np.ndarray) -> np.ndarray:
        """The refined camera-to-world poses (N, 4, 4) of `poses` (N, 4, 4), float64."""
        with torch.no_grad():
            frames = torch.arange(len(poses), device=self.twists.device)
            delta = self(torch.eye(4, device=self.twists.device).expand(len(poses), 4, 4), frames)
        return np.asarray(poses, dtype=np.float64) @ delta.double().cpu().numpy()


def follow_refinement(original: np.ndarray, refined: np.ndarray, others: np.ndarray) -> np.ndarray:
    """Poses `others` (M, 4, 4) moved by the rigid transform that best maps the `original`
    training poses (N, 4, 4) onto their `refined` versions, so that frames that were not
    refined (e.g. held-out ones) follow the frame shift that field and poses share. The fit
    uses each camera's centre and the points 1 m along its x, y and z axes (the centres
    alone do not fix rotation on a short, straight path)."""
    def anchors(poses):
        return np.concatenate([poses[:, :3, 3]] + [poses[:, :3, 3] + poses[:, :3, k] for k in range(3)])

    return rigid_alignment(anchors(original), anchors(refined)) @ others
