"""Faces fit for signed-distance queries and the eigenbasis: no degenerate or duplicate
triangles, consistent orientation.

Scans arrive with zero-area slivers, doubled triangles and patches of flipped faces. The
generalized winding number (the target's inside test, and the source's with
``source_sign="winding"``) depends on orientation: a flipped patch subtracts its solid angle,
and an inside-out mesh has winding number -1 inside, so every point would count as outside.
Degenerate triangles carry no surface, and duplicates count twice in the winding number and
in the cotangent Laplacian. The SDFs and the eigenbasis are therefore computed on a cleaned
copy of the faces; vertices, their order and the faces written on export are never changed.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, connected_components

from .errors import MeshValidationError
from .metrics import triangle_areas

__all__ = ["bridge_faces", "degenerate_faces", "duplicate_faces", "orient_faces", "sdf_faces"]

log = logging.getLogger(__name__)


def degenerate_faces(V, F, rel_area: float = 1e-14) -> np.ndarray:
    """Triangles with a repeated corner or a (near) zero area, ``(m,) bool``.

    Parameters
    ----------
    V : (n, 3) float
    F : (m, 3) int
    rel_area : float
        Twice the area below which a triangle counts as degenerate, relative to the squared
        bounding-box diagonal of ``V``.

    Examples
    --------
    >>> V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]])
    >>> degenerate_faces(V, np.array([[0, 1, 2], [0, 0, 1], [0, 1, 3]])).tolist()
    [False, True, True]
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    repeated = (F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 0] == F[:, 2])
    diag2 = float(np.sum((V.max(axis=0) - V.min(axis=0)) ** 2)) if len(V) else 0.0
    area2 = np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    return repeated | (area2 <= rel_area * diag2)


# an edge this many times the median edge spans the surface rather than lying on it: no
# data mesh of ../shared/data except the face poses has one over 15x (the face poses: 96-111x)
BRIDGE_RATIO = 20.0


def bridge_faces(V, F, ratio: float = BRIDGE_RATIO) -> np.ndarray:
    """Triangles with an edge over ``ratio`` times the mesh's median edge length, ``(m,) bool``:
    bridges across the surface (vertices scrambled in a file, a range image's depth jumps),
    or the long slivers of a CAD tessellation.

    Parameters
    ----------
    V : (n, 3) float
    F : (m, 3) int
    ratio : float

    Examples
    --------
    >>> V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [30, 0, 0.0]])
    >>> bridge_faces(V, [[0, 1, 2], [1, 3, 2], [0, 1, 2], [1, 4, 3]])
    array([False, False, False,  True])
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    edges = np.linalg.norm(V[F] - V[np.roll(F, 1, axis=1)], axis=2)  # (m, 3)
    return edges.max(axis=1) > ratio * np.median(edges)


def duplicate_faces(F) -> np.ndarray:
    """Triangles over the same three vertices as an earlier one (either orientation),
    ``(m,) bool``.

    Examples
    --------
    >>> duplicate_faces(np.array([[0, 1, 2], [2, 1, 0], [1, 2, 0], [0, 1, 3]])).tolist()
    [False, True, True, False]
    """
    F = np.asarray(F, dtype=np.int64)
    if len(F) == 0:
        return np.zeros(0, dtype=bool)
    _, first = np.unique(np.sort(F, axis=1), axis=0, return_index=True)
    dup = np.ones(len(F), dtype=bool)
    dup[first] = False
    return dup


def orient_faces(V, F) -> tuple[np.ndarray, int]:
    """Consistently oriented copy of ``F``, outward where a component encloses a volume.

    Triangles are connected through manifold edges (shared by exactly two triangles); within
    each connected patch every triangle is flipped, if needed, to agree with its neighbours
    (breadth-first from the patch's first triangle). A closed patch (each of its edges used by
    an even number of its own triangles) is then flipped whole if its signed volume
    (divergence theorem) is negative. An open patch (a scan's view, a mask, a surface with
    holes, a sheet bounded by non-manifold edges) encloses nothing, and its signed volume
    about any point says how it bends, not which way it faces: it keeps the orientation most
    of its area was given in (a range scan's triangles face the camera). Non-manifold edges
    do not connect patches.

    Parameters
    ----------
    V : (n, 3) float
    F : (m, 3) int

    Returns
    -------
    F : (m, 3) int64
        Same triangles in the same order, some with reversed corner order.
    flipped : int
        How many triangles were reversed.

    Examples
    --------
    >>> V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    >>> F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    >>> G, k = orient_faces(V, F[:, ::-1])         # an inside-out tetrahedron
    >>> k, bool(np.array_equal(G, F))
    (4, True)
    >>> G, k = orient_faces(V, F[[0, 1, 2]][:, ::-1])  # the tetrahedron's open cup, facing in
    >>> k                                            # as given: nothing says it is wrong
    0
    >>> orient_faces(V, np.r_[F[[0, 1]][:, ::-1], F[[2]]])[1]  # one of three against the others
    1
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.array(F, dtype=np.int64, copy=True)
    m = len(F)
    if m == 0:
        return F, 0
    # directed half-edges (a -> b) of every face, keyed by their undirected edge
    a = F[:, [0, 1, 2]].ravel()
    b = F[:, [1, 2, 0]].ravel()
    face = np.repeat(np.arange(m), 3)
    key = np.minimum(a, b) * (int(F.max()) + 1) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    key_s = key[order]
    start = np.flatnonzero(np.r_[True, key_s[1:] != key_s[:-1]])
    count = np.diff(np.r_[start, len(key_s)])
    pairs = start[count == 2]
    h0, h1 = order[pairs], order[pairs + 1]
    f0, f1 = face[h0], face[h1]
    # neighbours agree when they traverse the shared edge in opposite directions
    same = (a[h0] == a[h1]).astype(np.int8) + 1  # 1: consistent, 2: one must flip
    adj = sp.coo_matrix((np.r_[same, same], (np.r_[f0, f1], np.r_[f1, f0])), shape=(m, m)).tocsr()
    ncomp, labels = connected_components(adj, directed=False)
    # spanning forest: each face's predecessor towards its patch's first face (itself there)
    pred = np.arange(m)
    sizes = np.bincount(labels, minlength=ncomp)
    for c in np.flatnonzero(sizes > 1):
        root = int(np.argmax(labels == c))
        nodes, p = breadth_first_order(adj, root, directed=False, return_predecessors=True)
        pred[nodes[1:]] = p[nodes[1:]]
    # flip = XOR of the "must flip" marks on the path to the root, by pointer jumping
    flip = np.zeros(m, dtype=bool)
    tree = pred != np.arange(m)
    if tree.any():  # look the tree edges' marks up among the (face, face) pairs
        pair_key = np.r_[f0 * m + f1, f1 * m + f0]
        pair_same = np.r_[same, same]
        by_key = np.argsort(pair_key)
        at = np.searchsorted(pair_key[by_key], pred[tree] * m + np.flatnonzero(tree))
        flip[tree] = pair_same[by_key[at]] == 2
    for _ in range(64):
        if np.all(pred[pred] == pred):
            break
        flip = flip ^ flip[pred]
        pred = pred[pred]
    flip = flip ^ flip[pred]  # the root's own mark is False: a no-op once converged
    F[flip] = F[flip][:, ::-1]
    tri = V[F]
    centroid = np.stack([np.bincount(labels, tri[:, :, d].mean(axis=1), ncomp) for d in range(3)], 1)
    tri = tri - (centroid / sizes[:, None])[labels][:, None, :]
    det = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    # closed patches: outward, a positive signed volume (a flat one encloses nothing: as it is)
    inverted = np.bincount(labels, det, ncomp) < -1e-9 * np.bincount(labels, area, ncomp) ** 1.5
    # open patches (an edge of one triangle): the orientation of most of their given area
    # open patches: an edge used by an odd number of the patch's own triangles bounds it (an
    # edge of one triangle, or a non-manifold edge the patch meets once or three times)
    lab = labels[face]
    by_patch = np.lexsort((key, lab))
    k_p, l_p = key[by_patch], lab[by_patch]
    first = np.flatnonzero(np.r_[True, (k_p[1:] != k_p[:-1]) | (l_p[1:] != l_p[:-1])])
    uses = np.diff(np.r_[first, len(k_p)])
    open_patch = np.zeros(ncomp, dtype=bool)
    open_patch[l_p[first[uses % 2 == 1]]] = True
    against = np.bincount(labels, area * flip, ncomp) > 0.5 * np.bincount(labels, area, ncomp)
    reverse = np.where(open_patch, against, inverted)[labels]
    F[reverse] = F[reverse][:, ::-1]
    flip ^= reverse
    return F, int(flip.sum())


def sdf_faces(V, F, name: str = "mesh") -> np.ndarray:
    """The faces a signed-distance query of ``(V, F)`` should use.

    Degenerate (:func:`degenerate_faces`) and duplicate (:func:`duplicate_faces`) triangles
    are left out and the rest oriented consistently (:func:`orient_faces`); a warning says
    what changed. Triangles spanning the surface (:func:`bridge_faces`) are kept, with a
    warning when they hold over 1% of the area.

    Parameters
    ----------
    V : (n, 3) float
    F : (m, 3) int
    name : str
        Used in messages.

    Returns
    -------
    (k, 3) int64
        ``k <= m`` triangles indexing the same ``V``.

    Raises
    ------
    MeshValidationError
        If no triangle is left.
    """
    F = np.asarray(F, dtype=np.int64)
    degenerate = degenerate_faces(V, F)
    dup = duplicate_faces(F) & ~degenerate
    keep = ~(degenerate | dup)
    if not keep.any():
        raise MeshValidationError(f"{name}: every triangle is degenerate (zero area)")
    G, flipped = orient_faces(V, F[keep])
    _warn_bridges(V, G, name)
    if degenerate.any() or dup.any() or flipped:
        log.warning(
            "%s: for the signed distance, %d degenerate and %d duplicate triangles are left "
            "out and %d triangles reversed to a consistent orientation, outward where they "
            "enclose a volume (the mesh itself is unchanged)", name, int(degenerate.sum()),
            int(dup.sum()), flipped,
        )
    return G


def _warn_bridges(V, F, name: str, share: float = 0.01) -> None:
    """A warning when the triangles of :func:`bridge_faces` hold more than ``share`` of the
    area: they are part of the surface as given, and Eq. (3) fits the source to them."""
    bridges = bridge_faces(V, F)
    if not bridges.any():
        return
    area = triangle_areas(V, F)
    fraction = float(area[bridges].sum() / area.sum())
    if fraction > share:
        log.warning(
            "%s: %d triangles, %.0f%% of the area, have an edge over %g times the median edge: "
            "bridges across the surface (scrambled vertices, a range image's depth jumps)? They "
            "are registered to as part of the surface; remove them first if they are not "
            "(docs/bad_inputs.md)", name, int(bridges.sum()), 100 * fraction, BRIDGE_RATIO,
        )
