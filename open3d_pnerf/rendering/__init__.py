"""Rays, samplers and volume rendering."""

from .rays import Rays, intersect_aabb, make_rays, pixel_rays
from .samplers import BatchShare, bin_edges, depth_guided, importance, merge, stratified, uniform
from .volume import RayRender, SamplingConfig, composite, render_rays, render_weights, weight_quantile

__all__ = [
    "BatchShare", "RayRender", "Rays", "SamplingConfig", "bin_edges", "composite", "depth_guided", "importance",
    "intersect_aabb", "make_rays", "merge", "pixel_rays", "render_rays", "render_weights",
    "stratified",
    "uniform", "weight_quantile",
]
