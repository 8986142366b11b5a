"""Quality metrics of a registered mesh, shared by :func:`~morphmodes_vol.register`, the
baselines and the experiment scripts.

- ground-truth vertex error, when correspondence is known (shared/data README):
  ``mean_i ||x_i - y_i|| / bbox_diagonal(y)``;
- surface distance between the registered mesh and the target, symmetric mean and
  Hausdorff (max), relative to the target's bounding-box diagonal;
- SDF residual: RMS of ``f - g`` at the quadrature points (Eq. 3's integrand);
- degeneracy: fraction of collapsed triangles (area below 1% of their rest area), of flipped
  triangles (normal reversed relative to the rest normal mapped by the best affine fit of
  the deformation) and the volume ratio deformed / rest.

Every function takes arrays (``V (n, 3) float``, ``F (m, 3) int``) and returns plain floats
(or a dict of floats), so the numbers can go straight into a CSV or ``report.json``.
"""

from __future__ import annotations

import numpy as np

from .errors import MeshValidationError
from .mesh import bbox_diagonal
from .sdf.source import signed_volume

__all__ = [
    "ground_truth_error",
    "vertex_errors",
    "surface_distance",
    "sdf_residual",
    "triangle_areas",
    "edge_strain",
    "signed_volume",
    "best_affine_fit",
    "degeneracy",
    "shape_metrics",
    "COLLAPSE_FRACTION",
]

COLLAPSE_FRACTION = 0.01
"""A triangle has collapsed when its area is below this fraction of its rest area."""


def vertex_errors(registered: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per-vertex ground-truth error ``||registered_i - truth_i|| / bbox_diagonal(truth)``.

    Parameters
    ----------
    registered, truth : (n, 3) float
        Same vertex count and order.

    Returns
    -------
    (n,) float64

    Examples
    --------
    >>> import numpy as np
    >>> truth = np.array([[0, 0, 0], [3, 4, 0.0]])          # diagonal 5
    >>> vertex_errors(truth + [[0, 0, 1], [0, 0, 0]], truth)
    array([0.2, 0. ])
    """
    registered = np.asarray(registered, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    if registered.shape != truth.shape:
        raise MeshValidationError(
            f"ground truth has shape {truth.shape}, the registered mesh {registered.shape}: "
            "ground-truth error needs the same vertex count and order"
        )
    return np.linalg.norm(registered - truth, axis=1) / bbox_diagonal(truth)


def ground_truth_error(registered: np.ndarray, truth: np.ndarray) -> float:
    """``mean_i ||registered_i - truth_i|| / bbox_diagonal(truth)`` (shared/data README).

    Parameters
    ----------
    registered, truth : (n, 3) float
        Same vertex count and order.
    """
    return float(np.mean(vertex_errors(registered, truth)))


def surface_distance(V, F, Vt, Ft) -> dict[str, float]:
    """Symmetric surface distance between ``(V, F)`` and the target ``(Vt, Ft)``.

    Distances are measured from every vertex of one mesh to the closest point of the other
    surface, both ways (Open3D closest-point queries).

    Returns
    -------
    dict
        ``surface_mean``: the average of the two one-sided mean distances;
        ``surface_hausdorff``: the largest distance either way; both divided by the target's
        bounding-box diagonal.

    Examples
    --------
    >>> import numpy as np
    >>> V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]); F = np.array([[0, 1, 2]])
    >>> d = surface_distance(V + [0, 0, 0.5], F, V, F)     # target diagonal sqrt(2)
    >>> round(d["surface_mean"] * 2 ** 0.5, 6), round(d["surface_hausdorff"] * 2 ** 0.5, 6)
    (0.5, 0.5)
    """
    from .sdf import closest_points

    V = np.asarray(V, dtype=np.float64)
    Vt = np.asarray(Vt, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    Ft = np.asarray(Ft, dtype=np.int64)
    d_to_target = closest_points(Vt, Ft, V).distance
    d_to_source = closest_points(V, F, Vt).distance
    diag = bbox_diagonal(Vt)
    return {
        "surface_mean": float(0.5 * (d_to_target.mean() + d_to_source.mean()) / diag),
        "surface_hausdorff": float(max(d_to_target.max(), d_to_source.max()) / diag),
    }


def sdf_residual(V, F, Q, g, sign: str = "raycast") -> float:
    """RMS of ``f - g`` at the quadrature points ``Q (k, 3)``: ``f`` the signed distance of
    ``(V, F)``, ``g (k,)`` the target's (negative inside), in the units of ``Q``."""
    from .sdf import signed_distance

    f = signed_distance(np.asarray(V, dtype=np.float64), np.asarray(F, dtype=np.int64),
                        np.asarray(Q, dtype=np.float64), sign=sign).value
    return float(np.sqrt(np.mean((f - np.asarray(g, dtype=np.float64)) ** 2)))


def _cross(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    return np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])


def triangle_areas(V, F) -> np.ndarray:
    """Area of every triangle, ``(m,) float64``.

    Examples
    --------
    >>> triangle_areas([[0, 0, 0], [2, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    array([1.])
    """
    return 0.5 * np.linalg.norm(_cross(V, F), axis=1)


def edge_strain(V0, V, F) -> float:
    """Mean over the edges of ``|log(l / l0)|``, the stretch of every edge of the triangles
    ``F`` from ``V0 (n, 3)`` to ``V (n, 3)``: 0 for an isometry, invariant to rigid motions
    (not to scale). Each edge counts once per triangle side; a collapsed edge counts as a
    stretch of 1e-12.

    Examples
    --------
    >>> V0 = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0]]); F = np.array([[0, 1, 2]])
    >>> round(edge_strain(V0, V0 @ np.diag([2., 1, 1]), F), 4)  # log 2 on 1 edge, log(sqrt(5/2)) on 1
    0.3838
    """
    V0, V, F = np.asarray(V0, float), np.asarray(V, float), np.asarray(F, np.int64)
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    l0 = np.linalg.norm(V0[e[:, 0]] - V0[e[:, 1]], axis=1)
    l1 = np.linalg.norm(V[e[:, 0]] - V[e[:, 1]], axis=1)
    keep = l0 > 0
    return float(np.mean(np.abs(np.log(np.maximum(l1[keep], 1e-12 * l0[keep]) / l0[keep]))))


def best_affine_fit(X0, X) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares affine map ``x ~ A x0 + t`` from ``X0 (n, 3)`` to ``X (n, 3)``.

    Returns
    -------
    A : (3, 3) float64
    t : (3,) float64
    """
    X0 = np.asarray(X0, dtype=np.float64)
    X = np.asarray(X, dtype=np.float64)
    H = np.hstack([X0, np.ones((X0.shape[0], 1))])
    sol, *_ = np.linalg.lstsq(H, X, rcond=None)  # (4, 3): x^T = [x0^T 1] sol
    return sol[:3].T.copy(), sol[3].copy()


def degeneracy(X0, X, F, collapse: float = COLLAPSE_FRACTION) -> dict[str, float]:
    """Degeneracy of the deformation ``X0 -> X`` of a mesh with triangles ``F``.

    Parameters
    ----------
    X0, X : (n, 3) float
        Rest and deformed vertices (same order).
    F : (m, 3) int
    collapse : float
        A triangle has collapsed when its area is below ``collapse`` times its rest area.

    Returns
    -------
    dict
        ``collapsed_fraction``: fraction of triangles (with a non-zero rest area) that
        collapsed; ``flipped_fraction``: fraction of the triangles that did not collapse whose
        normal points against the rest normal mapped by the best affine fit ``A`` of the
        whole deformation (normals map by the
        cofactor matrix ``det(A) A^-T``, so a global reflection or an affine stretch is not
        counted as a flip); ``volume_ratio``: deformed / rest signed volume (NaN when the rest
        volume is zero).

    Examples
    --------
    >>> import numpy as np
    >>> V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    >>> F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    >>> degeneracy(V, 2 * V, F)
    {'collapsed_fraction': 0.0, 'flipped_fraction': 0.0, 'volume_ratio': 8.0}
    """
    X0 = np.asarray(X0, dtype=np.float64)
    X = np.asarray(X, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    if X0.shape != X.shape:
        raise MeshValidationError(f"rest vertices {X0.shape} and deformed vertices {X.shape} differ in shape")
    n0 = _cross(X0, F)
    n1 = _cross(X, F)
    a0 = 0.5 * np.linalg.norm(n0, axis=1)
    a1 = 0.5 * np.linalg.norm(n1, axis=1)
    valid = a0 > 0
    m = max(int(valid.sum()), 1)
    collapsed = valid & (a1 < collapse * a0)
    A, _ = best_affine_fit(X0, X)
    # cofactor of A, det(A) A^-T (columns a2 x a3, a3 x a1, a1 x a2): maps the cross product of
    # two rest edges to that of the mapped edges; defined for singular A too (planar meshes)
    a1, a2, a3 = A.T
    cof = np.column_stack([np.cross(a2, a3), np.cross(a3, a1), np.cross(a1, a2)])
    expected = n0 @ cof.T
    flipped = valid & ~collapsed & (np.einsum("ij,ij->i", expected, n1) < 0)
    v0 = signed_volume(X0, F)
    return {
        "collapsed_fraction": float(collapsed.sum() / m),
        "flipped_fraction": float(flipped.sum() / m),
        "volume_ratio": float(signed_volume(X, F) / v0) if v0 != 0 else float("nan"),
    }


def shape_metrics(X0, X, F, Vt, Ft, truth=None) -> dict[str, float]:
    """Surface distance to the target, degeneracy and, when ``truth (n, 3)`` is given, the
    ground-truth error, of a registered mesh ``(X, F)`` with rest pose ``X0``. All inputs in
    one frame (any: every number is relative or a fraction)."""
    out = surface_distance(X, F, Vt, Ft)
    out.update(degeneracy(X0, X, F))
    if truth is not None:
        out["ground_truth_error"] = ground_truth_error(X, truth)
    return out
