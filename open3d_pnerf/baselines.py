"""Deprecated module name: the TSDF code lives in :mod:`open3d_pnerf.tsdf`."""

import warnings

from .tsdf import TSDFVolume, tsdf_fusion  # noqa: F401

warnings.warn("open3d_pnerf.baselines is deprecated; import from open3d_pnerf.tsdf (or open3d_pnerf)",
              DeprecationWarning, stacklevel=2)
