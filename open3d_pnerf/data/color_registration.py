"""Colour images onto the depth image's pixel grid, for a camera whose colour camera has its own
intrinsic and may sit apart from its depth camera (7-Scenes' Kinect; a colour_extrinsic given to
load_sequence)."""

from __future__ import annotations

import dataclasses
import functools

import cv2
import numpy as np
from scipy import ndimage

from ..errors import InputError


@dataclasses.dataclass(frozen=True, eq=False)
class ColorRig:
    """A colour camera against a depth camera's pixel grid: K_depth, K_color (3, 3) their intrinsic
    matrices at the same image scale, rig (4, 4) the transform from depth-camera to colour-camera
    coordinates (m), size (H, W) of the depth grid."""

    K_depth: np.ndarray
    K_color: np.ndarray
    rig: np.ndarray
    size: tuple[int, int]

    def resample(self, color: np.ndarray, depth: np.ndarray | None, what: str) -> np.ndarray:
        """The colour image (H_c, W_c, 3) resampled onto the depth grid (H, W, 3).

        depth: the frame's depth (H, W) m, needed when the rig moves the colour camera's centre:
        each depth pixel then takes the colour where its point projects in the colour camera (pixels
        without depth take the depth of the nearest pixel with it; a frame without any, the plane at
        infinity). Occlusion is not tested: a point the colour camera cannot see takes the colour of
        what hides it. When the two cameras share a centre the depth is not needed. `what` names the
        sequence in errors."""
        translation = self.rig[:3, 3]
        if not translation.any():
            return cv2.remap(color, *self.plane_maps, cv2.INTER_LINEAR)
        if depth is None:
            raise InputError(f"{what}: color_on_depth_grid() needs the frame's depth: its colour camera "
                             "is offset from the depth camera (color_extrinsic)")
        depth = np.asarray(depth)
        h, w = self.size
        if depth.shape != (h, w):
            raise InputError(f"{what}: color_on_depth_grid() got depth {depth.shape[1]}x{depth.shape[0]}, "
                             f"expected the depth grid's {w}x{h}")
        if not (depth > 0).any():
            return cv2.remap(color, *self.plane_maps, cv2.INTER_LINEAR)
        nearest = ndimage.distance_transform_edt(depth <= 0, return_distances=False, return_indices=True)
        offset = translation / depth[tuple(nearest)][..., None]  # the camera's offset over each point's z
        return cv2.remap(color, *self.maps(offset), cv2.INTER_LINEAR)

    def maps(self, offset) -> tuple[np.ndarray, np.ndarray]:
        """(map_x, map_y) float32 (H, W): where each depth pixel's point lands in the colour image,
        the point being its ray at z = 1 turned into the colour camera plus `offset` ((3,) or
        (H, W, 3): the colour camera's offset over the point's depth-camera z)."""
        kd, kc = self.K_depth, self.K_color
        h, w = self.size
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        rays = np.stack([(u - kd[0, 2]) / kd[0, 0], (v - kd[1, 2]) / kd[1, 1], np.ones_like(u)], -1)
        points = rays @ self.rig[:3, :3].T + offset
        map_x = kc[0, 0] * points[..., 0] / points[..., 2] + kc[0, 2]
        map_y = kc[1, 1] * points[..., 1] / points[..., 2] + kc[1, 2]
        return map_x.astype(np.float32), map_y.astype(np.float32)

    @functools.cached_property
    def plane_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """The colour maps of the plane at infinity: every frame's when the cameras share a centre
        (computed once per sequence, not on every frame load)."""
        return self.maps(np.zeros(3))
