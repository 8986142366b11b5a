"""The target SDF, computed once on a dense grid and sampled by trilinear interpolation."""

from __future__ import annotations

import logging

import numpy as np

from .grid import Grid, trilinear_sample
from .source import SignMethod, signed_distance

__all__ = ["DenseTargetSDF"]

log = logging.getLogger(__name__)

# Query the BVH in chunks to bound the memory of Open3D's result tensors.
_CHUNK = 1 << 20


class DenseTargetSDF:
    """Signed distance of the target on a regular grid (negative inside).

    Parameters
    ----------
    grid : Grid
        The nodes.
    values : (nx, ny, nz) float
        Signed distance at the nodes.

    Examples
    --------
    >>> import trimesh
    >>> s = trimesh.creation.icosphere(3)
    >>> sdf = DenseTargetSDF.from_mesh(s.vertices, s.faces, Grid.covering([-1.2] * 3, [1.2] * 3, 25))
    >>> bool(abs(sdf.sample(np.array([[0.0, 0.0, 0.0]]))[0] + 1) < 0.02)
    True
    """

    def __init__(self, grid: Grid, values: np.ndarray):
        self.grid = grid
        self.values = np.asarray(values, dtype=np.float64).reshape(grid.shape)

    @classmethod
    def from_mesh(cls, V, F, grid: Grid, sign: SignMethod = "winding") -> "DenseTargetSDF":
        """Evaluate the signed distance of ``(V, F)`` at every node of ``grid``.

        ``sign="winding"`` (default) decides inside by the generalized winding number, which
        stays correct behind holes of an open target; ``"raycast"`` uses ray parity.
        """
        P = grid.points()
        values = np.empty(P.shape[0])
        for start in range(0, P.shape[0], _CHUNK):
            chunk = P[start : start + _CHUNK]
            values[start : start + len(chunk)] = signed_distance(V, F, chunk, sign=sign).value
        log.debug("target SDF: %s nodes, spacing %.4g", grid.shape, grid.spacing)
        return cls(grid, values.reshape(grid.shape))

    def sample(self, points: np.ndarray) -> np.ndarray:
        """Trilinear interpolation at ``points (k, 3)``; returns ``(k,)``."""
        return trilinear_sample(self.values, self.grid, points)

    @property
    def nbytes(self) -> int:
        return int(self.values.nbytes)
