"""Occupancy, free space and distance for a planner, from the probabilistic model.

``recon.occupancy(points)`` and ``recon.occupancy_grid(voxel_size)`` (an :class:`OccupancyGrid`:
probabilities, free / occupied / unknown, an Open3D voxel grid, OctoMap files, a distance field and
collision probabilities). How the probability is derived: :mod:`.evidence`; how right it is on
held-out views: :mod:`.scoring`.
"""

from .distance import DistanceField, collision_probability, distance_field, signed_distance
from .evidence import MIN_EVIDENCE, SensorModel, ViewEvidence, occupancy_at, occupancy_grid, view_evidence
from .grid import FREE_BELOW, OCCUPIED_ABOVE, OccupancyGrid, grid_frame
from .scoring import calibration, heldout_voxels, voxel_centers, voxel_codes

__all__ = ["FREE_BELOW", "MIN_EVIDENCE", "OCCUPIED_ABOVE", "DistanceField", "OccupancyGrid", "SensorModel",
           "ViewEvidence", "collision_probability", "distance_field", "grid_frame", "occupancy_at", "occupancy_grid",
           "signed_distance", "view_evidence", "calibration", "heldout_voxels", "voxel_centers", "voxel_codes"]
