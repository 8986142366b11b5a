"""Where the SDF of an open target is known: the confidence that weights Eq. (3).

A closed target's signed distance is known everywhere. An open one's (a partial scan, a
mask, a surface with holes) is known near its surface and in front of it, on the side its
normals face (the side a scanner looked from): there is empty space, or the surface. Behind
the observed surface, farther than a band, the field is a guess: the distance to the part
that was seen, and a sign that the winding number makes up. Eq. (3) there would pull the
unseen parts of the source onto an invented surface, so its quadrature weights are
multiplied by

    c(q) = max(front(q), phi(d(q) / b)),
    front(q) = smoothstep((q - p) . n / d(q), -s, s),   phi(t) = max(0, 1 - t^2)^2,

``p`` the closest point of the target to ``q``, ``n`` the normal of its triangle, ``d(q) =
|q - p|`` and ``b`` the band (a few grid spacings): 1 in front and near the surface, 0 behind
it and far, continuous in between. A closed target: ``c = 1`` (no weights).
"""

from __future__ import annotations

import numpy as np

from .grid import Grid
from .source import closest_points, is_closed
from .target import DenseTargetSDF

__all__ = ["target_confidence", "front_cosine"]

_SLOPE = 0.2  # front: the cosine over which the weight goes from 0 to 1


def _smoothstep(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def front_cosine(V, F, Q, closest) -> np.ndarray:
    """The cosine between ``q - p`` and the normal of the triangle of ``p``, ``(k,)``, for
    each point ``q`` of ``Q (k, 3)`` and its closest point ``p`` on the mesh ``(V, F)``
    (``closest``, :func:`~morphmodes_vol.sdf.source.closest_points` of ``Q``): 1 straight in
    front of the surface, -1 straight behind it, near 0 beside its rim.

    Examples
    --------
    >>> from morphmodes_vol.primitives import icosphere
    >>> V, F = icosphere(2)
    >>> cap = F[V[F].mean(axis=1)[:, 2] > 0]
    >>> Q = np.array([[0, 0, 1.4], [0, 0, 0.5]])
    >>> np.round(front_cosine(V, cap, Q, closest_points(V, cap, Q)), 1)  # above, inside
    array([ 1., -1.])
    """
    normal = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    d = np.maximum(closest.distance, 1e-300)
    return np.einsum("ij,ij->i", Q - closest.points, normal[closest.faces]) / d


def target_confidence(V, F, grid: Grid, band: float) -> DenseTargetSDF | None:
    """The confidence ``c`` of the module docstring on the nodes of ``grid`` (sampled
    trilinearly between them), or ``None`` for a closed target.

    Parameters
    ----------
    V : (n, 3) float
    F : (f, 3) int
        Consistently oriented (:func:`morphmodes_vol.repair.sdf_faces`), normals out of the
        scanned body.
    grid : Grid
    band : float
        ``b``, a length.

    Examples
    --------
    >>> from morphmodes_vol.primitives import icosphere
    >>> V, F = icosphere(3)
    >>> cap = F[V[F].mean(axis=1)[:, 2] > 0]               # the upper half, seen from above
    >>> c = target_confidence(V, cap, Grid.covering([-1.5] * 3, [1.5] * 3, 13), band=0.2)
    >>> np.round(c.sample(np.array([[0, 0, 1.4], [0, 0, 0.0], [0, 0, -1.4]])), 2)  # above, inside, below
    array([1., 0., 0.])
    >>> target_confidence(V, F, Grid.covering([-1.5] * 3, [1.5] * 3, 5), band=0.2) is None
    True
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    if is_closed(F):
        return None
    Q = grid.points()
    cp = closest_points(V, F, Q)
    near = np.maximum(0.0, 1 - (cp.distance / band) ** 2) ** 2
    c = np.maximum(_smoothstep(front_cosine(V, F, Q, cp), -_SLOPE, _SLOPE), near)
    return DenseTargetSDF(grid, c.reshape(grid.shape))
