"""Lumped (diagonal) mass matrix."""

from __future__ import annotations

from typing import Literal

import numpy as np
import scipy.sparse as sp

from ..errors import OptionError
from ..mesh import validate_mesh

__all__ = ["lumped_mass"]


def lumped_mass(V, F, kind: Literal["voronoi", "barycentric"] = "voronoi") -> sp.csc_matrix:
    """Diagonal mass matrix ``M`` of a triangle mesh (libigl's ``massmatrix``).

    Parameters
    ----------
    V : (n, 3) float
    F : (m, 3) int
    kind : {"voronoi", "barycentric"}
        ``"voronoi"``: mixed Voronoi areas (Meyer et al. 2003); ``"barycentric"``: one third
        of the area of every incident triangle. Both sum to the surface area.

    Returns
    -------
    M : (n, n) scipy.sparse.csc_matrix of float64, diagonal
    """
    import igl

    V, F = validate_mesh(V, F, "lumped_mass input")
    if kind == "voronoi":
        mtype = igl.MASSMATRIX_TYPE_VORONOI
    elif kind == "barycentric":
        mtype = igl.MASSMATRIX_TYPE_BARYCENTRIC
    else:
        raise OptionError(f"lumped_mass kind={kind!r}: expected one of ('voronoi', 'barycentric')")
    M = igl.massmatrix(V, F, mtype)
    return sp.diags(np.asarray(M.diagonal(), dtype=np.float64)).tocsc()
