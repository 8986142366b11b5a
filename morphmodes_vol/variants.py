"""The same shape, delivered otherwise: jittered, re-triangulated, densified, noisy, partial.

What a scanner or another mesher makes of one surface. A registration's result should not
depend on which of these it is given beyond what the geometry itself changes; the
robustness study (``scripts/robustness_study.py``) and the tests use them to check that.
Every function takes ``V (n, 3) float, F (m, 3) int`` and returns new arrays (the inputs
are never modified); randomness comes from ``seed``.
"""

from __future__ import annotations

import numpy as np

from .mesh import bbox_diagonal, validate_mesh
from .repair import bridge_faces

__all__ = ["jittered", "retriangulated", "densified", "noisy", "partial_view", "half_view_direction", "sampled_points", "VARIANTS",
           "target_variant"]

VARIANTS = ("original", "retriangulated", "dense", "noisy", "partial", "no-bridges")
"""The target variants of the robustness study, in its order (the study runs the first five
unless asked for ``no-bridges``)."""


def jittered(V, sigma: float, seed: int) -> np.ndarray:
    """``V`` with every coordinate moved by ``N(0, (sigma * diagonal)^2)``, ``(n, 3)``;
    ``sigma`` relative to the bounding-box diagonal. ``seed=0`` or ``sigma=0``: a copy.

    Examples
    --------
    >>> V = np.eye(3)
    >>> bool(np.abs(jittered(V, 1e-7, seed=1) - V).max() < 1e-5), bool((jittered(V, 1e-7, 0) == V).all())
    (True, True)
    """
    V = np.array(V, dtype=np.float64)
    if seed == 0 or sigma == 0:
        return V
    rng = np.random.default_rng(seed)
    return V + rng.normal(scale=sigma * bbox_diagonal(V), size=V.shape)


def retriangulated(V, F, fraction: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """The surface re-meshed by quadric decimation (Open3D,
    ``simplify_quadric_decimation``) to about ``fraction`` of its triangles."""
    import open3d as o3d

    V, F = validate_mesh(V, F, "mesh")
    if not 0 < fraction <= 1:
        raise ValueError(f"fraction must lie in (0, 1], got {fraction}")
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(F.astype(np.int32)))
    out = mesh.simplify_quadric_decimation(target_number_of_triangles=max(4, int(round(fraction * len(F)))))
    out.remove_unreferenced_vertices()
    return np.asarray(out.vertices, dtype=np.float64), np.asarray(out.triangles, dtype=np.int64)


def densified(V, F, splits: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Every triangle split into ``splits`` (a power of 4) by midpoint subdivision (trimesh
    ``remesh.subdivide``): the same surface, more and smaller triangles."""
    from trimesh.remesh import subdivide

    V, F = validate_mesh(V, F, "mesh")
    times = int(round(np.log(splits) / np.log(4)))
    if splits < 1 or 4**times != splits:
        raise ValueError(f"splits must be a power of 4, got {splits}")
    for _ in range(times):
        V, F = subdivide(V, F)
    return np.asarray(V, dtype=np.float64), np.asarray(F, dtype=np.int64)


def _vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals, ``(n, 3)`` (zero where a vertex has no area)."""
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    N = np.zeros_like(V)
    for k in range(3):
        np.add.at(N, F[:, k], n)
    length = np.linalg.norm(N, axis=1, keepdims=True)
    return np.divide(N, length, out=np.zeros_like(N), where=length > 0)


def noisy(V, F, sigma: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Every vertex moved along its normal by ``N(0, (sigma * diagonal)^2)``; the faces as
    given. ``sigma`` relative to the bounding-box diagonal."""
    V, F = validate_mesh(V, F, "mesh")
    rng = np.random.default_rng(seed)
    offset = rng.normal(scale=sigma * bbox_diagonal(V), size=len(V))
    return V + offset[:, None] * _vertex_normals(V, F), F


def half_view_direction(V, F) -> np.ndarray:
    """A view direction that sees about half of the surface: of the principal axes of ``V``,
    from the least spread (a side view of an elongated body) to the most, the first from which
    the triangles facing it hold 35-65% of the area (else the one nearest half), signed so
    that its largest component is positive. A mask seen from the front shows nearly all of
    itself: its view is from the side."""
    V, F = validate_mesh(V, F, "mesh")
    _, vectors = np.linalg.eigh(np.cov((V - V.mean(0)).T))  # ascending spread
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    area = np.linalg.norm(n, axis=1)
    best, gap = None, np.inf
    for axis in vectors.T:
        axis = axis if axis[np.argmax(np.abs(axis))] > 0 else -axis
        share = area[n @ axis > 0].sum() / area.sum()
        if abs(share - 0.5) <= 0.15:
            return axis
        if abs(share - 0.5) < gap:
            best, gap = axis, abs(share - 0.5)
    return best


def partial_view(V, F, direction=None) -> tuple[np.ndarray, np.ndarray]:
    """The triangles facing ``direction`` (seen from there: ``n . direction > 0``; default
    :func:`half_view_direction`), with only their vertices."""
    V, F = validate_mesh(V, F, "mesh")
    d = half_view_direction(V, F) if direction is None else np.asarray(direction, dtype=np.float64)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    Fk = F[n @ d > 0]
    if len(Fk) == 0:
        raise ValueError("no triangle faces that direction")
    used, Fc = np.unique(Fk, return_inverse=True)
    return V[used], Fc.reshape(-1, 3).astype(np.int64)


def sampled_points(V, F, count: int, noise: float = 0.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points drawn uniformly by area on the surface, with the unit normals of their
    triangles, each moved along its normal by ``N(0, (noise * diagonal)^2)``: a full scan as
    a point cloud. Returns ``points, normals``, both ``(count, 3)``.

    Examples
    --------
    >>> from morphmodes_vol.primitives import icosphere
    >>> P, N = sampled_points(*icosphere(3), 2000, seed=1)
    >>> bool(np.abs(np.linalg.norm(P, axis=1) - 1).max() < 0.01), bool((np.sum(P * N, axis=1) > 0.9).all())
    (True, True)
    """
    V, F = validate_mesh(V, F, "mesh")
    rng = np.random.default_rng(seed)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    area = np.linalg.norm(n, axis=1)
    face = rng.choice(len(F), size=count, p=area / area.sum())
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    T = V[F[face]]
    P = T[:, 0] + u[:, None] * (T[:, 1] - T[:, 0]) + v[:, None] * (T[:, 2] - T[:, 0])
    N = n[face] / np.maximum(area[face], 1e-300)[:, None]
    P = P + rng.normal(scale=noise * bbox_diagonal(V), size=count)[:, None] * N
    return P, N


def target_variant(V, F, variant: str, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """One of :data:`VARIANTS` of the target ``(V, F)``, as the robustness study defines it:
    ``retriangulated`` to 25% of the faces; ``dense``, each face split into 16; ``noisy``,
    re-triangulated then moved along the normals by 0.3% of the diagonal; ``partial``, the
    faces facing :func:`half_view_direction`; ``no-bridges``, without the triangles that span
    the surface (:func:`morphmodes_vol.repair.bridge_faces`)."""
    if variant == "original":
        return validate_mesh(V, F, "mesh")
    if variant == "retriangulated":
        return retriangulated(V, F, 0.25)
    if variant == "dense":
        return densified(V, F, 16)
    if variant == "noisy":
        return noisy(*retriangulated(V, F, 0.25), sigma=3e-3, seed=seed + 1)
    if variant == "partial":
        return partial_view(V, F)
    if variant == "no-bridges":
        V, F = validate_mesh(V, F, "mesh")
        return V, F[~bridge_faces(V, F)]
    raise ValueError(f"variant {variant!r}: expected one of {VARIANTS}")
