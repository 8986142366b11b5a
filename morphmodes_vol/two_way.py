"""Correspondences from the reverse registration (``two_way``; docs/method.md, "Two-way").

Registering the target onto the source deforms the target mesh ``(Y, G)`` into ``Yd``, which
lies on the source's surface. Each source vertex ``x_i`` then has a counterpart on the
target: find the closest point of the deformed target to ``x_i`` (a face of ``G`` and
barycentrics ``b``) and take the same barycentric point of the *undeformed* target,
``p_i = sum_c b_c Y[G[f, c]]`` (:func:`reverse_correspondences`). Read the other way, each
deformed target vertex ``Yd_j`` has a closest point on the source's surface, which should land
on ``Y_j``. Both are closest points as barycentric rows (:func:`closest_point_rows`).
:meth:`Registration.run` fits the subspace to the first, and to both stacked
(:meth:`~morphmodes_vol.eigenbasis.LBSBasis.fit`), and lets Levenberg-Marquardt minimize the
objective from each fit: starts that the forward runs cannot reach on some poses.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .sdf import closest_points

__all__ = ["reverse_correspondences", "closest_point_rows"]


def reverse_correspondences(X: np.ndarray, deformed: np.ndarray, faces: np.ndarray,
                            rest: np.ndarray) -> np.ndarray:
    """Where each point of ``X`` lands on the target, read off a registration of the
    target onto ``X``'s surface.

    Parameters
    ----------
    X : (n, 3) float
        Source vertices (the frame of ``deformed``).
    deformed : (k, 3) float
        The target's vertices after registering the target onto the source.
    faces : (g, 3) int
        The target's faces.
    rest : (k, 3) float
        The target's vertices as given (the frame the output is in).

    Returns
    -------
    (n, 3) float64
        For each ``X[i]``: the point of ``(rest, faces)`` with the barycentric coordinates, on
        the same face, of the closest point of ``(deformed, faces)`` to ``X[i]``.

    Examples
    --------
    >>> tri = np.array([[0, 1, 2]]); Y = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0]])
    >>> reverse_correspondences(np.array([[0.25, 0.25, 0.5]]), Y, tri, 2 * Y + [0, 0, 1])
    array([[0.5, 0.5, 1. ]])
    """
    rest = np.asarray(rest, dtype=np.float64)
    if np.shape(deformed) != rest.shape:
        raise ValueError(f"deformed {np.shape(deformed)} and rest {rest.shape} vertices differ in shape")
    return closest_point_rows(deformed, faces, X) @ rest


def closest_point_rows(X: np.ndarray, faces: np.ndarray, points: np.ndarray) -> sp.csr_matrix:
    """The closest point of the mesh ``(X, faces)`` to each of ``points``, as a row of
    barycentric coordinates over the mesh's vertices: ``rows @ X`` are those closest points,
    and ``rows @ x`` the same surface points after the vertices move to ``x``.

    Parameters
    ----------
    X : (n, 3) float
    faces : (f, 3) int
    points : (k, 3) float

    Returns
    -------
    (k, n) scipy.sparse.csr_matrix
        Three entries per row, summing to 1.

    Examples
    --------
    >>> tri = np.array([[0, 1, 2]]); X = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0]])
    >>> closest_point_rows(X, tri, np.array([[0.5, 0.5, 2.0]])).toarray()
    array([[0. , 0.5, 0.5]])
    """
    X = np.asarray(X, dtype=np.float64)
    faces = np.asarray(faces)
    cp = closest_points(X, faces, np.asarray(points, dtype=np.float64))
    k = cp.faces.shape[0]
    return sp.csr_matrix((cp.barycentrics.ravel(), faces[cp.faces].ravel(), np.arange(0, 3 * k + 1, 3)),
                         shape=(k, X.shape[0]))
