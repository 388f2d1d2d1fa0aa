"""Per-frame camera exposure: frame i records gain_i * C of a rendered colour C, a gain per channel.

Real RGB-D cameras change exposure and white balance as they move (the TUM fr1/xyz camera
darkens as the sequence goes on, differently per channel: tests/test_reconstruction.py). Without a model of it
the field has to average the frames' exposures into one colour per point, or bend its
geometry to fake the differences. The field learns the scene at the training frames'
average exposure, and a learned gain per training frame and channel turns it into what that
frame recorded. Gains are exp(l_i - mean_j l_j): the mean log-gain over the training frames
is zero, so field and gains cannot trade a common factor.
"""

from __future__ import annotations

import numpy as np
import torch


class ExposureGains(torch.nn.Module):
    """Colour gains of N training frames, (N, 3) per-channel log-gains starting at 0 (gain 1)."""

    def __init__(self, n_frames: int, device="cpu"):
        super().__init__()
        self.log_gains = torch.nn.Parameter(torch.zeros(n_frames, 3, device=device))

    def gains(self) -> torch.Tensor:
        """(N, 3) gains, geometric mean 1 over the frames for each channel."""
        return torch.exp(self.log_gains - self.log_gains.mean(0, keepdim=True))

    def forward(self, color: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
        """Colours (R, 3) in [0, 1] as frames (R,) recorded them, clipped at 1 like a saturated pixel."""
        return (color * self.gains()[frames]).clamp(max=1.0)


def interpolate_gains(known_times: np.ndarray, known_gains: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Gains (M, 3) at `times` (M,) from frames with gains (N, 3) at `known_times` (N,):
    log-linear in time between the nearest known frames, the nearest one's beyond the ends.
    Exposure drifts with the camera's view, so a held-out frame most likely has that of the
    training frames around it."""
    order = np.argsort(known_times, kind="stable")
    t, log_g = np.asarray(known_times, np.float64)[order], np.log(np.asarray(known_gains, np.float64)[order])
    return np.exp(np.stack([np.interp(times, t, log_g[:, c]) for c in range(log_g.shape[1])], 1))
