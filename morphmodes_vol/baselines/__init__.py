"""Baselines of the paper's comparisons, with the conventions of :func:`~morphmodes_vol.register`:
registered vertices in the source's original frame and vertex order, the source's faces,
``timings`` (seconds) and ``metrics`` (:mod:`morphmodes_vol.metrics`, same keys).

- :func:`rigid_icp`: rigid ICP (trimesh ``registration.icp``'s iteration on Open3D closest points,
  no reflection, no scale);
- :func:`nricp`: non-rigid ICP of Amberg et al. 2007 (trimesh ``registration.nricp_amberg``),
  alone or after rigid ICP (``rigid_first=True``, the paper's RICP+NRICP);
  :func:`nricp_onto_points` the same onto a point cloud (a scan);
- :func:`full_space_sdf`: the SDF energy of Eq. (3) optimized over every vertex, optionally
  with the Dirichlet regularizer ``1/2 (x - x0)^T L (x - x0)`` (the paper's "Necessity of
  adaptive scheme");
- :func:`fixed_subspace`: the SDF energy in a fixed subspace of ``k`` skinning eigenmodes.
"""

from .fixed_subspace import fixed_subspace
from .full_space import full_space_sdf
from .icp import nricp, nricp_onto_points, rigid_icp
from .result import BaselineResult, PreparedPair, prepare_pair

__all__ = [
    "BaselineResult",
    "PreparedPair",
    "prepare_pair",
    "rigid_icp",
    "nricp",
    "nricp_onto_points",
    "full_space_sdf",
    "fixed_subspace",
]
