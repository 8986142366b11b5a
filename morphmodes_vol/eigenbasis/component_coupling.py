"""A stiffness that joins the connected components of a mesh, so that its skinning
eigenmodes are defined by its shape.

The cotangent Laplacian of a mesh of ``c`` components has a null space of dimension ``c``:
every function constant on each component. Its first ``c`` eigenvectors are then any basis of
that space, which the eigensolver picks from the last bits of its input (a jitter of 1e-7
changes it), and none of them bends a component. Parts that touch (the eyes and the feathers
of a cartoon chicken, the buttons of a coat) move together in any pose, so the eigenproblem
is solved with the Laplacian plus a coupling of every vertex to the surface of the other
components near it,

    E_link(u) = sum_i m_i / (h^2 + d_i^2) * (u_i - ubar_i)^2,
    ubar_i = sum_j a_ij u_j,   a_ij = m_j phi(d_ij / R_i) / sum_l m_l phi(d_il / R_i),

``m_i`` the vertex's lumped mass (its share of the area), ``d_i`` its distance to the nearest
vertex of another component, ``h`` a length (a fraction of the bounding-box diagonal), and
``ubar_i`` a mass-weighted average over the ``k`` nearest vertices ``j`` of other components,
``phi(t) = (1 - t^2)^2`` with ``R_i`` the distance to the ``(k+1)``-th: touching parts are
stitched as firmly as stretches of surface a length ``h`` apart, distant parts weakly. Every
weight changes continuously with the geometry: ``d_i`` is a minimum of distances, and a
neighbour enters or leaves the ``k`` with weight zero (where a nearest-vertex link would jump
between two equidistant vertices). The term is a surface integral, so it does not depend on
the triangulation. One component: no coupling.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..mesh import bbox_diagonal, validate_mesh

__all__ = ["component_coupling"]


def _components(n: int, F: np.ndarray) -> tuple[int, np.ndarray]:
    edges = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    A = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    return connected_components(A, directed=False)


def component_coupling(V, F, mass, length: float = 0.01, neighbours: int = 8) -> sp.csr_matrix | None:
    """The coupling stiffness ``K (n, n)`` of the module docstring (a graph Laplacian, symmetric
    positive semidefinite), or ``None`` for a connected mesh.

    Parameters
    ----------
    V : (n, 3) float
    F : (f, 3) int
        Every vertex referenced (as after :func:`~morphmodes_vol.eigenbasis.mesh_skinning_weights`'s
        cleaning).
    mass : (n,) float
        Lumped mass of each vertex.
    length : float
        ``h``, relative to the bounding-box diagonal.
    neighbours : int
        ``k``, the vertices of other components each vertex is coupled to.

    Returns
    -------
    (n, n) scipy.sparse.csr_matrix or None

    Examples
    --------
    >>> V = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [3, 0, 0], [4, 0, 0], [3, 1, 0]])
    >>> K = component_coupling(V, [[0, 1, 2], [3, 4, 5]], np.ones(6), length=0.1)
    >>> bool(abs(K.sum()) < 1e-12), K.shape           # a Laplacian: rows sum to zero
    (True, (6, 6))
    >>> K = component_coupling(V, [[0, 1, 2], [3, 4, 5]], np.ones(6), length=0.1, neighbours=1)
    >>> # k = 1: vertices 1 and 3, 2 apart, each other's nearest across: two links of 1 / (h^2 + 4)
    >>> bool(np.isclose(-K[1, 3], 2 / ((0.1 * np.sqrt(17)) ** 2 + 4)))
    True
    """
    V, F = validate_mesh(V, F, "mesh")
    n = V.shape[0]
    count, label = _components(n, F)
    if count == 1:
        return None
    mass = np.asarray(mass, dtype=np.float64)
    k = int(neighbours)
    rows = np.arange(n)
    # the k + 1 nearest vertices of other components of every vertex: from the nearest of
    # all vertices where enough of them are on other components, else from a tree of those
    want = k + 1
    near = min(n, 4 * want)
    dist, idx = cKDTree(V).query(V, near)
    dist, idx = dist.reshape(n, near), idx.reshape(n, near)
    across = label[idx] != label[:, None]
    enough = across.sum(axis=1) >= want
    D = np.full((n, want), np.inf)
    J = np.zeros((n, want), dtype=np.int64)
    if enough.any():
        order = np.argsort(~across[enough], axis=1, kind="stable")[:, :want]  # the first `want` across
        D[enough] = np.take_along_axis(dist[enough], order, axis=1)
        J[enough] = np.take_along_axis(idx[enough], order, axis=1)
    for c in np.unique(label[~enough]):
        here = np.flatnonzero((label == c) & ~enough)
        others = np.flatnonzero(label != c)
        m = min(want, len(others))
        d, j = cKDTree(V[others]).query(V[here], m)
        D[here, :m], J[here, :m] = d.reshape(len(here), m), others[j.reshape(len(here), m)]
    # the kernel's radius: the (k+1)-th distance (where fewer vertices lie across: twice the
    # farthest), so the k-th's weight goes to zero before it leaves the k
    found = np.isfinite(D)
    R = np.where(found[:, k], D[:, k], 2 * np.max(np.where(found, D, 0), axis=1))
    D, J, found = D[:, :k], J[:, :k], found[:, :k]
    t = np.where(found, D / np.maximum(R, np.finfo(float).tiny)[:, None], 1.0)
    a = mass[J] * (1 - np.minimum(t, 1.0) ** 2) ** 2
    total = a.sum(axis=1, keepdims=True)
    # all k at the radius (equidistant): an equal share each
    a = np.where(total > 0, a / np.where(total > 0, total, 1.0), found / found.sum(axis=1, keepdims=True))
    h = length * bbox_diagonal(V)
    w = (mass / (h * h + D[:, 0] ** 2))[:, None] * a  # (n, k): vertex i to its neighbour J[i, l]
    i = np.repeat(rows, k)
    w, j = w.ravel(), J.ravel()
    keep = w > 0
    i, j, w = i[keep], j[keep], w[keep]
    K = sp.coo_matrix((np.r_[-w, -w], (np.r_[i, j], np.r_[j, i])), shape=(n, n)).tocsr()
    return (K - sp.diags(np.asarray(K.sum(axis=1)).ravel())).tocsr()
