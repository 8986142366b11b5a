"""Size limits: refuse a registration early, with a memory estimate, instead of running out of
memory after minutes.

The estimate is a fixed overhead plus a sum of per-item costs in bytes, read off the code
and checked to bound the peak resident memory of real runs from above by 1.1-2x
(``scripts/memory_check.py``, numbers in docs/bad_inputs.md):

- every quadrature point, during one energy evaluation: the point, the target value, Open3D's
  float32 copies and results, closest triangles, barycentrics and the Ericson region tests
  (about 40 float64 temporaries);
- every target-grid node: its coordinates and value, plus the temporaries of one chunk of at
  most 2^20 nodes of signed-distance queries;
- every source vertex: the cotangent Laplacian and its shift-invert factorization (sparse
  LU fill-in), the mesh cleaning and the eigensolver's Lanczos vectors; the dense solver
  (below 600 vertices) needs ``n^2`` matrices instead;
- every source vertex and mode: the skinning weights and their copies;
- every face of source and target: Open3D's BVH and the cleaning passes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from .errors import OptionError

__all__ = ["MemoryEstimate", "estimate_memory", "check_memory"]

log = logging.getLogger(__name__)

BASE = 250_000_000  # first use of Open3D, libigl and the BLAS thread pools (measured ~200 MB)
BYTES_PER_QUADRATURE_POINT = 400
BYTES_PER_TARGET_NODE = 80
BYTES_PER_TARGET_CHUNK_NODE = 200
TARGET_CHUNK = 1 << 20  # nodes per batch of target queries (sdf/target.py)
BYTES_PER_VERTEX = 2000
BYTES_PER_VERTEX_MODE = 64
BYTES_PER_FACE = 400
DENSE_EIGEN_LIMIT = 600  # eigenbasis/skinning_eigenmodes.py
GB = 1e9


@dataclass(frozen=True)
class MemoryEstimate:
    """Peak memory of a registration, in bytes, by item (an upper-bound estimate).

    Attributes
    ----------
    base, quadrature, target_grid, eigenbasis, faces : int
    """

    base: int
    quadrature: int
    target_grid: int
    eigenbasis: int
    faces: int

    @property
    def total(self) -> int:
        return self.base + self.quadrature + self.target_grid + self.eigenbasis + self.faces

    def describe(self) -> str:
        """``"about 12.31 GB (libraries 0.25, quadrature 1.20, ... GB)"``."""
        return (
            f"about {self.total / GB:.2f} GB (libraries {self.base / GB:.2f}, "
            f"quadrature {self.quadrature / GB:.2f}, "
            f"target grid {self.target_grid / GB:.2f}, eigenbasis {self.eigenbasis / GB:.2f}, "
            f"faces {self.faces / GB:.2f} GB)"
        )


def estimate_memory(n_vertices: int, n_faces: int, n_target_faces: int, modes: int,
                    quadrature_points: int, target_nodes: int) -> MemoryEstimate:
    """Estimated peak memory of a registration (see the module docstring).

    Parameters
    ----------
    n_vertices, n_faces : int
        Size of the source.
    n_target_faces : int
    modes : int
        ``m_max``.
    quadrature_points, target_nodes : int
        Points of the quadrature grid and nodes of the target-SDF grid.

    Examples
    --------
    >>> e = estimate_memory(5000, 10000, 10000, 20, 64**3, 64**3)
    >>> round(e.total / 1e9, 2)
    0.45
    """
    n = int(n_vertices)
    if n <= DENSE_EIGEN_LIMIT:
        eigen = 4 * 8 * n * n + BYTES_PER_VERTEX * n
    else:
        eigen = BYTES_PER_VERTEX * n
    eigen += BYTES_PER_VERTEX_MODE * n * int(modes)
    return MemoryEstimate(
        base=BASE,
        quadrature=BYTES_PER_QUADRATURE_POINT * int(quadrature_points),
        target_grid=BYTES_PER_TARGET_NODE * int(target_nodes)
        + BYTES_PER_TARGET_CHUNK_NODE * min(int(target_nodes), TARGET_CHUNK),
        eigenbasis=eigen,
        faces=BYTES_PER_FACE * (int(n_faces) + int(n_target_faces)),
    )


def check_memory(estimate: MemoryEstimate, limit_gb: float | None, what: str) -> None:
    """Raise :class:`OptionError` when ``estimate`` exceeds ``limit_gb`` (``None``: no limit).

    Parameters
    ----------
    estimate : MemoryEstimate
    limit_gb : float or None
    what : str
        The sizes that led to the estimate, for the message.
    """
    log.info("memory estimate for %s: %s", what, estimate.describe())
    if limit_gb is not None and estimate.total > limit_gb * GB:
        raise OptionError(
            f"{what} would need {estimate.describe()}, above the limit of {limit_gb:g} GB "
            "(option memory_limit_gb, --set memory_limit_gb=GB): lower the grid or the modes, simplify "
            "the mesh, or raise the limit"
        )
