"""PNeRFModel: the field with everything that turns it into images of the training frames.

The model owns the field, the samplers' settings, the loss method, and, when training, the
training cameras, a colour gain per training frame (exposure) and a rigid correction per
training pose. ``forward(batch)`` renders a :class:`~open3d_pnerf.batches.RayBatch` of
training pixels as their frames recorded them; ``loss(renders, batch, weights)`` returns the
loss terms; ``render(rays)`` renders any rays without gradient (deterministic samples).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from torch import nn
from torch.profiler import record_function

from .batches import RayBatch
from .fields.sdf import depth_sdf_loss, eikonal_loss, eikonal_points, surface_distance
from .losses import LossMethod, LossWeights, loss_method, total_loss
from .pose_refinement import PoseCorrections, follow_refinement
from .rendering import BatchShare, RayRender, Rays, SamplingConfig, make_rays, render_rays
from .rendering.exposure import ExposureGains, interpolate_gains

VIEW_COLOR_MIN_WEIGHT = 1e-4
"""Renders for viewing colour only the samples whose weight reaches this: one below adds less than
it to the pixel (at most 0.004 in all with 40 samples); densities, depth and opacity are exact."""


class PNeRFModel(nn.Module):
    """field: a scene field; sampling: samples per ray; loss: a name in LOSSES or a LossMethod;
    coarse_terms: the loss also scores the coarse render (the paper's coarse + fine terms;
    ObjectiveConfig.coarse_terms); coarse_color: it scores the coarse render's colour alone
    (ObjectiveConfig.coarse_color).

    For training, give the training cameras: poses (N, 4, 4) camera-to-world and K (3, 3),
    and optionally exposure (an ExposureGains of the N frames) and pose_corrections (a
    PoseCorrections of the N frames, weighted by pose_prior_weight in the loss).
    depth_range: (2,) [near, far] z-depth every ray is clipped to besides the scene box (an
    image-only scene's SfM bounds), or None.
    """

    def __init__(self, field: nn.Module, sampling: SamplingConfig, loss: str | LossMethod = "pnerf", *,
                 coarse_terms: bool = False, coarse_color: bool = False, poses: torch.Tensor | None = None,
                 K: torch.Tensor | None = None, exposure: ExposureGains | None = None,
                 pose_corrections: PoseCorrections | None = None, pose_prior_weight: float = 0.0,
                 depth_range: torch.Tensor | None = None):
        super().__init__()
        self.field = field
        self.sampling = sampling
        self.loss_method = loss_method(loss)
        self.coarse_terms = coarse_terms
        self.coarse_color = coarse_color
        self.exposure = exposure
        self.pose_corrections = pose_corrections
        self.pose_prior_weight = pose_prior_weight
        self.register_buffer("train_poses", poses, persistent=False)
        self.register_buffer("K", K, persistent=False)
        self.register_buffer("depth_range", depth_range, persistent=False)

    @property
    def device(self) -> torch.device:
        return self.field.aabb.device

    # -- training --------------------------------------------------------------------------
    def rays(self, batch: RayBatch) -> Rays:
        """The world rays of training pixels, from their frames' (corrected) poses, in the scene box."""
        poses = self.train_poses[batch.frames]
        if self.pose_corrections is not None:
            poses = self.pose_corrections(poses, batch.frames)
        return make_rays(poses, self.K, batch.u, batch.v, self.field.aabb, depth_range=self.depth_range)

    def forward(self, batch: RayBatch, generator: torch.Generator | BatchShare | None = None) -> list[RayRender]:
        """[fine] or [fine, coarse] renders of the batch's pixels, with each frame's exposure.

        generator: the random numbers' source (a BatchShare renders rows of a larger batch
        exactly as the whole batch would). Rays with a depth target get depth-guided samples
        when the loss has depth terms and sampling.depth_guided is set."""
        guide = bool(self.loss_method.terms) and self.sampling.depth_guided
        with record_function("pnerf.rays"):
            rays = self.rays(batch)
        fine, coarse = render_rays(self.field, rays, self.sampling, batch.mean if guide else None,
                                   batch.sigma if guide else None, generator,
                                   with_coarse=self.coarse_terms or self.coarse_color)
        renders = [fine] + ([coarse] if coarse is not None else [])
        if self.exposure is not None:  # the colours as each ray's frame recorded them
            renders = [dataclasses.replace(r, color=self.exposure(r.color, batch.frames)) for r in renders]
        return renders

    def loss(self, renders: list[RayRender], batch: RayBatch, weights: LossWeights,
             n_rays: int | None = None, n_target: int | None = None) -> dict:
        """Loss terms of :func:`~open3d_pnerf.losses.total_loss`, plus, for a signed distance field,
        the eikonal term (at points in the box and along the batch's rays) and the depth targets'
        direct terms sdf_surface and sdf_free (with a loss that has depth terms;
        :func:`~open3d_pnerf.fields.sdf.depth_sdf_loss`: they move the field, not the poses), and the
        pose prior when poses are refined. n_rays, n_target: the whole batch's counts when `batch` is one rank's share."""
        terms = total_loss(self.loss_method, renders, batch.rgb, batch.mean, batch.sigma, weights, n_rays, n_target,
                           batch.weight, depth_renders=None if self.coarse_terms else 1)
        share = 1.0 if n_rays is None else len(batch) / n_rays  # this rank's part of the batch
        sdf = getattr(self.field, "sdf", None)
        if sdf is not None:
            rays = self.rays(batch)
            origins, directions = rays.origins.detach(), rays.directions.detach()
            if weights.eikonal > 0:
                points = eikonal_points(self.field.aabb, origins, directions, rays.near, rays.far,
                                        max(1, round(sdf.eikonal_points * share)))
                terms["eikonal"] = eikonal_loss(self.field.signed_distance, points, sdf.eikonal_step)
                terms["loss"] = terms["loss"] + weights.eikonal * terms["eikonal"] * share
            if (weights.sdf_surface > 0 or weights.sdf_free > 0) and self.loss_method.terms:
                has = torch.isfinite(batch.mean)
                direct = depth_sdf_loss(self.field.signed_distance, origins[has], directions[has], rays.near[has],
                                        batch.mean[has], batch.sigma[has], batch.weight[has], sdf.truncation,
                                        sdf.band_points if weights.sdf_surface > 0 else 0,
                                        sdf.free_points if weights.sdf_free > 0 else 0, self.field.inside)
                part = has.sum() / max(n_target if n_target is not None else int(has.sum()), 1)
                for name, value in direct.items():
                    terms[name] = value
                    terms["loss"] = terms["loss"] + getattr(weights, name) * value * part
        if self.pose_corrections is not None:  # each share of a batch adds its part of the prior
            terms["pose_prior"] = self.pose_corrections.prior()
            terms["loss"] = terms["loss"] + self.pose_prior_weight * terms["pose_prior"] * share
        return terms

    # -- rendering ---------------------------------------------------------------------------
    @torch.no_grad()
    def render(self, rays: Rays, chunk: int = 2048, keys: tuple = ("color", "depth", "depth_var", "opacity")) -> dict:
        """Render rays in chunks without gradient, for viewing, evaluation and export: samples in
        the middle of their slices (deterministic), the guided ones drawn as importance samples
        (no targets here), colour only where a sample's weight reaches VIEW_COLOR_MIN_WEIGHT
        (see :func:`~open3d_pnerf.rendering.volume.render_rays`).

        Samples as :meth:`SamplingConfig.for_render` says (more coarse ones than training uses).
        Returns the :class:`~open3d_pnerf.rendering.RayRender` fields named by `keys`: by default
        color (R, 3), depth (R,) expected ray distance, depth_var (R,), opacity (R,); also
        median (R,) median ray distance, t (R, S), edges (R, S + 1), weights (R, S) with
        S = max(n_coarse, n_coarse_render) + n_fine + n_guided; for a signed-distance field also
        surface (R,) the ray distance of its first zero crossing (NaN where the ray meets none,
        :func:`~open3d_pnerf.fields.sdf.surface_distance`).
        """
        outs = {k: [] for k in keys}
        sampling = self.sampling.for_render()
        for start in range(0, len(rays), chunk):
            part = rays[start : start + chunk]
            render, _ = render_rays(self.field, part, sampling, jitter=False, color_min_weight=VIEW_COLOR_MIN_WEIGHT)
            for k in outs:
                outs[k].append(self._surface(part, render) if k == "surface" else getattr(render, k))
        return {k: torch.cat(v) for k, v in outs.items()}

    def _surface(self, rays: Rays, render: RayRender) -> torch.Tensor:
        if getattr(self.field, "sdf", None) is None:
            raise TypeError("render(): 'surface' is the zero crossing of a signed-distance field (geometry='sdf')")
        return surface_distance(self.field.signed_distance, rays.origins, rays.directions, render.t, render.density,
                                self.field.beta)

    def frames_after_training(self, poses: np.ndarray, timestamps: np.ndarray, train_idx: np.ndarray,
                              hold_idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The poses (N, 4, 4) and colour gains (N, 3) of every frame of a sequence with `poses`
        and `timestamps` (N,) s after training: the refined training poses (`poses` as they are
        without pose refinement), the held-out frames moved by the shift the refinement gave the
        training frames; the learned exposure gains of the training frames, interpolated in time
        for the held-out ones (ones without exposure compensation)."""
        if self.pose_corrections is not None:
            refined = self.pose_corrections.corrected(poses[train_idx])
            poses = poses.copy()
            poses[hold_idx] = follow_refinement(poses[train_idx], refined, poses[hold_idx])
            poses[train_idx] = refined
        gains = np.ones((len(timestamps), 3))
        if self.exposure is not None:
            gains[train_idx] = self.exposure.gains().detach().double().cpu().numpy()
            gains[hold_idx] = interpolate_gains(timestamps[train_idx], gains[train_idx], timestamps[hold_idx])
        return poses, gains

    def camera_rays(self, pose, K, u: torch.Tensor, v: torch.Tensor) -> Rays:
        """Rays of pixels (u, v) (R,) of a camera-to-world pose (4, 4) with intrinsic matrix K
        (3, 3), clipped to the scene box."""
        pose = torch.as_tensor(np.array(pose, np.float32), device=self.device)
        K = torch.as_tensor(np.array(K, np.float32), device=self.device)
        return make_rays(pose, K, u, v, self.field.aabb, depth_range=self.depth_range)


def build_model(config, aabb, poses: np.ndarray | None = None, K: np.ndarray | None = None,
                covariances: np.ndarray | None = None, depth_range=None, blocks=None, tables=None,
                field: nn.Module | None = None, warp=None) -> PNeRFModel:
    """The model of a ReconstructionConfig over the scene box aabb (2, 3): the field (seeded by config.seed,
    on config.device; blocks, tables: the boxes and log2 table sizes of a field that grew, see
    ReconstructionConfig.build_field; warp: its NDCWarp or None; or the given `field`, to train further) and, given the training
    cameras (poses (N, 4, 4), K (3, 3), pose covariances (N, 6, 6)), the exposure gains and pose
    corrections the config asks for; depth_range: (2,) z-depth [near, far] of every ray, or None."""
    field = config.build_field(aabb, blocks, tables, warp) if field is None else field
    device = field.aabb.device
    if depth_range is not None:
        depth_range = torch.as_tensor(np.asarray(depth_range), dtype=torch.float32, device=device)
    cameras, exposure, corrections = {}, None, None
    if poses is not None:
        cameras = dict(poses=torch.as_tensor(np.asarray(poses), dtype=torch.float32, device=device),
                       K=torch.as_tensor(np.asarray(K), dtype=torch.float32, device=device))
        if config.refine_poses:
            corrections = PoseCorrections(covariances, device)
        if config.exposure_compensation:
            exposure = ExposureGains(len(poses), device)
    objective = config.objective
    return PNeRFModel(field, config.sampling, config.loss, coarse_terms=objective.coarse_terms,
                      coarse_color=objective.coarse_color, exposure=exposure,
                      pose_corrections=corrections, pose_prior_weight=objective.pose_prior_weight,
                      depth_range=depth_range, **cameras)
