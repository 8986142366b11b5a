"""Skinning weights for any source mesh a user brings: welded seams, triangle soups (STL),
unreferenced vertices, zero-area triangles and meshes of several components."""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import ArpackError
from scipy.spatial import cKDTree

from ..errors import MeshValidationError
from ..mesh import bbox_diagonal, validate_mesh
from ..repair import degenerate_faces
from .component_coupling import component_coupling
from .lumped_mass import lumped_mass
from .skinning_eigenmodes import skinning_eigenmodes

__all__ = ["mesh_skinning_weights"]

log = logging.getLogger(__name__)


def _weld(V: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Clusters of vertices chained by pairs closer than ``tol`` (not cells of a lattice,
    whose boundaries would part two copies of a vertex moved by a rounding error), each welded
    to its lowest index: the kept vertices ``(k,)`` and each vertex's cluster ``(n,)``."""
    n = V.shape[0]
    pairs = cKDTree(V).query_pairs(tol, output_type="ndarray")
    _, cluster = connected_components(sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                                                    shape=(n, n)), directed=False)
    _, first, inverse = np.unique(cluster, return_index=True, return_inverse=True)
    return first, inverse.ravel()


def mesh_skinning_weights(V, F, modes: int, seed: int = 0, weld_tolerance: float = 1e-9
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Skinning eigenmodes (Eq. 4) of ``(V, F)``, computed on a cleaned copy of the mesh and
    mapped back to every input vertex.

    Cleaning, so that the cotangent Laplacian is well defined and connected where the surface
    is: vertices closer than ``weld_tolerance`` times the bounding-box diagonal are welded
    (UV seams, STL triangle soups), triangles with a repeated corner or zero area are left
    out, and only referenced vertices enter the eigenproblem. Vertices left out get the
    weights of the nearest vertex that entered it, so welded copies move together. A mesh of
    several components has its components joined by
    :func:`~morphmodes_vol.eigenbasis.component_coupling.component_coupling`, so that its
    modes bend the shape rather than move its parts apart (and do not depend on how the
    eigensolver picks a basis of the Laplacian's null space).

    Parameters
    ----------
    V : (n, 3) float
    F : (f, 3) int
    modes : int
    seed : int
    weld_tolerance : float
        Relative to the bounding-box diagonal.

    Returns
    -------
    W : (n, modes) float64
        ``W^T M W = I`` for the mass matrix of the cleaned mesh.
    eigenvalues : (modes,) float64

    Raises
    ------
    MeshValidationError
        If fewer than ``modes`` (or 4) vertices remain after cleaning.

    Examples
    --------
    >>> import trimesh
    >>> s = trimesh.creation.icosphere(1)
    >>> soup = s.vertices[s.faces].reshape(-1, 3)          # what an STL file holds
    >>> W, lam = mesh_skinning_weights(soup, np.arange(len(soup)).reshape(-1, 3), 4)
    >>> W.shape, bool(lam[1] > 1e-3)                        # connected again: one zero eigenvalue
    ((240, 4), True)
    """
    V, F = validate_mesh(V, F, "source")
    n = V.shape[0]
    first, inverse = _weld(V, weld_tolerance * max(bbox_diagonal(V), np.finfo(float).tiny))
    Vw = V[first]
    Fw = inverse[F]
    degenerate = degenerate_faces(Vw, Fw)
    Fw = Fw[~degenerate]
    if Fw.shape[0] == 0:
        raise MeshValidationError("source: every triangle is degenerate (zero area)")
    used = np.unique(Fw)
    if used.size < max(modes, 4):
        raise MeshValidationError(
            f"source: {used.size} usable vertices after welding and dropping degenerate "
            f"triangles, fewer than the {max(modes, 4)} needed for {modes} modes"
        )
    compact = np.full(Vw.shape[0], -1, dtype=np.int64)
    compact[used] = np.arange(used.size)
    Vc, Fc = Vw[used], compact[Fw]
    coupling = component_coupling(Vc, Fc, lumped_mass(Vc, Fc).diagonal())
    try:
        Wc, lam = skinning_eigenmodes(Vc, Fc, modes, seed=seed, coupling=coupling)
    except (ArpackError, np.linalg.LinAlgError, RuntimeError) as exc:  # no convergence, singular
        raise MeshValidationError(
            f"source: the skinning eigenproblem could not be solved ({type(exc).__name__}: {exc}); "
            "try another seed (--set seed=1), fewer --modes, or remesh the source"
        ) from None

    # each input vertex -> welded vertex -> row of Wc; welded vertices not in the
    # eigenproblem take the row of the nearest one that is
    row = compact[inverse]
    missing = row < 0
    if missing.any():
        _, nearest = cKDTree(Vw[used]).query(V[missing])
        row[missing] = nearest
    if n > Vw.shape[0] or degenerate.any() or missing.any():
        log.warning("source mesh cleaned for the eigenbasis: %d vertices welded, %d degenerate "
                    "triangles left out, %d vertices outside the eigenproblem (they follow their "
                    "nearest vertex)", n - Vw.shape[0], int(degenerate.sum()), int(missing.sum()))
    return Wc[row], lam
