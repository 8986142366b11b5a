"""Cotangent Laplacian (positive semidefinite convention)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..mesh import validate_mesh

__all__ = ["cotangent_laplacian"]


def cotangent_laplacian(V, F) -> sp.csc_matrix:
    """Cotangent Laplacian ``L`` of a triangle mesh, positive semidefinite.

    ``L[i, j] = -(cot a_ij + cot b_ij) / 2`` for an edge ``ij`` and ``L[i, i] = -sum_j
    L[i, j]``, so ``x^T L x >= 0`` and constants are in the null space. Assembled by libigl
    (``igl.cotmatrix``, which is negative semidefinite; we flip its sign).

    Parameters
    ----------
    V : (n, 3) float
        Vertex positions.
    F : (m, 3) int
        Triangles.

    Returns
    -------
    L : (n, n) scipy.sparse.csc_matrix of float64

    Examples
    --------
    >>> import numpy as np
    >>> V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    >>> F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    >>> L = cotangent_laplacian(V, F)
    >>> bool(abs(L @ np.ones(4)).max() < 1e-12)
    True
    """
    import igl

    V, F = validate_mesh(V, F, "cotangent_laplacian input")
    L = -igl.cotmatrix(V, F)
    L = sp.csc_matrix(L, dtype=np.float64)
    # Exact symmetry (libigl's assembly is symmetric up to round-off).
    return sp.csc_matrix(0.5 * (L + L.T))
