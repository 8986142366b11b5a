"""Generated shapes and known deformations for the demo and the tests."""

from __future__ import annotations

import numpy as np

__all__ = ["capsule", "icosphere", "holed_sphere", "bend", "affine"]


def capsule(height: float = 1.0, radius: float = 0.25, count: tuple[int, int] = (24, 24)) -> tuple[np.ndarray, np.ndarray]:
    """A closed capsule along z (trimesh's ``creation.capsule``), centred at the origin.

    Returns
    -------
    V : (n, 3) float64
    F : (m, 3) int64
    """
    import trimesh

    m = trimesh.creation.capsule(height=height, radius=radius, count=list(count))
    V = np.asarray(m.vertices, dtype=np.float64)
    return V - (V.max(axis=0) + V.min(axis=0)) / 2, np.asarray(m.faces, dtype=np.int64)


def icosphere(subdivisions: int = 2, radius: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A unit icosphere. Returns ``V (n, 3) float64, F (m, 3) int64``."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


def holed_sphere(subdivisions: int = 4, hole_angles=(0.2, 0.35, 0.5)) -> tuple[np.ndarray, np.ndarray]:
    """A unit icosphere with round holes of several sizes: an open target for sign tests.

    Hole ``i`` removes the faces whose centroid lies within angle ``hole_angles[i]`` (radians)
    of a fixed direction (the directions are spread over the sphere). With the defaults,
    518 of 5120 faces are removed.

    Returns
    -------
    V : (n, 3) float64
        All vertices of the icosphere (those of removed faces stay, unreferenced).
    F : (m, 3) int64
    """
    V, F = icosphere(subdivisions)
    dirs = np.array([[1.0, 0.2, 0.1], [-0.3, 1.0, 0.4], [0.2, -0.5, -1.0], [-1.0, -0.6, 0.3]])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    c = V[F].mean(axis=1)
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    keep = np.ones(len(F), dtype=bool)
    for d, angle in zip(dirs, hole_angles):
        keep &= c @ d < np.cos(angle)
    return V, F[keep]


def bend(V: np.ndarray, angle: float, axis: int = 2, towards: int = 0) -> np.ndarray:
    """Bend a shape lying along ``axis`` into a circular arc of total angle ``angle``.

    The centre line (coordinate ``axis``, from its minimum to its maximum) is mapped onto an
    arc of the same length in the ``(towards, axis)`` plane, keeping cross-sections normal
    to it: a smooth, near-isometric deformation.

    Parameters
    ----------
    V : (n, 3) float
    angle : float
        Radians; 0 is the identity.

    Returns
    -------
    (n, 3) float64
    """
    V = np.array(V, dtype=np.float64, copy=True)
    if angle == 0:
        return V
    s = V[:, axis] - V[:, axis].min()
    length = s.max()
    R = length / angle  # radius of the arc
    theta = s / R
    u = V[:, towards]
    out = V.copy()
    out[:, towards] = (R - u) * -np.cos(theta) + R
    out[:, axis] = (R - u) * np.sin(theta) + V[:, axis].min()
    return out


def affine(V: np.ndarray, A: np.ndarray, t) -> np.ndarray:
    """``V @ A.T + t`` for ``A (3, 3)`` and ``t (3,)``; returns ``(n, 3)``."""
    return np.asarray(V, dtype=np.float64) @ np.asarray(A, dtype=np.float64).T + np.asarray(t, dtype=np.float64)
