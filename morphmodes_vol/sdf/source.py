"""Signed distance of a (deforming) triangle mesh at query points, with what its gradient
needs: the closest triangle and the barycentric coordinates of the closest point.

The closest triangle is found by Open3D's BVH (``RaycastingScene.compute_closest_points``,
float32); the closest point on that triangle is then recomputed in float64 so the distance
is a smooth function of the vertex positions between closest-feature switches. The sign
comes from an inside test: ray-parity occupancy (``compute_occupancy``), negative inside,
or the generalized winding number; ``"unsigned"`` keeps the distance unsigned (an open
surface has no inside, and a scan may see either of its sides: docs/decisions/0023). Ray
parity does not see the orientation of the triangles; with ``oriented=True`` the sign of
the enclosed volume (:func:`signed_volume`) supplies it, so that a surface turned inside
out (a deformation through a reflection) has its inside outside (docs/decisions/0017).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..errors import OptionError
from .closest_point import closest_point_barycentrics

__all__ = ["ClosestPoints", "SignedDistanceQuery", "closest_points", "signed_distance", "signed_volume",
           "is_closed", "resolve_sign"]

SignMethod = Literal["raycast", "winding"]
"""An inside test: what a target's field and a closed or holed source's are signed by."""
DistanceSign = Literal["raycast", "winding", "unsigned"]
"""How :func:`signed_distance` signs: an inside test, or none (an open source, decision 0023)."""


@dataclass(frozen=True)
class ClosestPoints:
    """Closest points of a mesh to query points.

    Attributes
    ----------
    faces : (k,) int64
        Index of the closest triangle.
    barycentrics : (k, 3) float64
        Closest point ``= sum_c barycentrics[:, c] * V[F[faces, c]]``.
    points : (k, 3) float64
        The closest points.
    distance : (k,) float64
        Unsigned distance from the query point.
    """

    faces: np.ndarray
    barycentrics: np.ndarray
    points: np.ndarray
    distance: np.ndarray


def _scene(V: np.ndarray, F: np.ndarray):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(V, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(F, dtype=np.uint32)),
    )
    return scene


def closest_points(V: np.ndarray, F: np.ndarray, Q: np.ndarray, scene=None) -> ClosestPoints:
    """Closest point on the mesh ``(V, F)`` to each query point.

    Parameters
    ----------
    V : (n, 3) float
    F : (m, 3) int
    Q : (k, 3) float
    scene : open3d.t.geometry.RaycastingScene, optional
        A scene already holding ``(V, F)``, to avoid rebuilding the BVH.

    Returns
    -------
    ClosestPoints
    """
    import open3d as o3d

    if scene is None:
        scene = _scene(V, F)
    ans = scene.compute_closest_points(o3d.core.Tensor(np.ascontiguousarray(Q, dtype=np.float32)))
    faces = ans["primitive_ids"].numpy().astype(np.int64)
    tri = F[faces]
    bary = closest_point_barycentrics(Q, V[tri[:, 0]], V[tri[:, 1]], V[tri[:, 2]])
    points = np.einsum("kc,kcd->kd", bary, V[tri])
    distance = np.linalg.norm(Q - points, axis=1)
    return ClosestPoints(faces=faces, barycentrics=bary, points=points, distance=distance)


def inside(V: np.ndarray, F: np.ndarray, Q: np.ndarray, method: SignMethod = "raycast",
           scene=None, samples: int = 1) -> np.ndarray:
    """Inside test, ``(k,) bool``.

    ``"raycast"``: Open3D ray-parity occupancy with ``samples`` rays (majority vote); exact
    for closed meshes. ``"winding"``: generalized winding number > 1/2 (libigl's fast
    winding number), robust to holes and non-manifold targets.
    """
    if method == "raycast":
        import open3d as o3d

        if scene is None:
            scene = _scene(V, F)
        occ = scene.compute_occupancy(
            o3d.core.Tensor(np.ascontiguousarray(Q, dtype=np.float32)), nsamples=samples
        )
        return occ.numpy() > 0.5
    if method == "winding":
        import igl

        w = igl.fast_winding_number(
            np.ascontiguousarray(V, dtype=np.float64),
            np.ascontiguousarray(F, dtype=np.int64),
            np.ascontiguousarray(Q, dtype=np.float64),
        )
        return np.asarray(w) > 0.5
    raise OptionError(f"inside test {method!r}: expected one of ('raycast', 'winding')")


@dataclass(frozen=True)
class SignedDistanceQuery:
    """Signed distance at query points and its spatial gradient.

    Attributes
    ----------
    value : (k,) float64
        Signed distance, negative inside.
    normal : (k, 3) float64
        ``grad_q f``: unit vector from the closest point to the query, times the sign
        (the face normal where the distance is zero).
    closest : ClosestPoints
    """

    value: np.ndarray
    normal: np.ndarray
    closest: ClosestPoints


def is_closed(F) -> bool:
    """Whether every undirected edge of the triangles ``F (f, 3)`` is shared by exactly two
    (closed and edge-manifold).

    Examples
    --------
    >>> is_closed([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]]), is_closed([[0, 1, 2]])
    (True, False)
    """
    F = np.asarray(F, dtype=np.int64)
    edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool(np.all(counts == 2))


def resolve_sign(F, sign: str) -> DistanceSign:
    """``sign``, with ``"auto"`` made ray parity for a closed mesh (:func:`is_closed`) and
    the generalized winding number otherwise.

    Examples
    --------
    >>> resolve_sign([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]], "auto"), resolve_sign([[0, 1, 2]], "auto")
    ('raycast', 'winding')
    """
    if sign == "auto":
        return "raycast" if is_closed(F) else "winding"
    return sign


def signed_volume(V, F) -> float:
    """Signed volume enclosed by the triangles ``F (m, 3)`` at the vertices ``V (n, 3)``
    (the divergence theorem, a sum of tetrahedra on the origin): positive for a closed
    surface oriented outward, negative for the same surface inside out.

    Examples
    --------
    >>> V = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
    >>> F = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]
    >>> round(signed_volume(V, F), 12), round(signed_volume(V, [f[::-1] for f in F]), 12)
    (0.166666666667, -0.166666666667)
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    return float(np.einsum("ij,ij->", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]]))) / 6.0


def signed_distance(V: np.ndarray, F: np.ndarray, Q: np.ndarray, sign: DistanceSign = "raycast",
                    samples: int = 1, oriented: bool = False) -> SignedDistanceQuery:
    """Signed distance of the mesh ``(V, F)`` at ``Q (k, 3)``, negative inside; ``sign`` as
    :func:`inside` decides it, ``"unsigned"`` (the distance, ``>= 0``), or ``"auto"``
    (:func:`resolve_sign`).

    ``oriented``: the orientation of the triangles decides which side is inside. Ray parity
    does not see it; with ``oriented`` its sign is flipped when the enclosed volume
    (:func:`signed_volume`) is negative: a closed surface oriented outward at rest and
    turned inside out by a deformation (a reflection) then has its SDF negated, not
    unchanged. The winding number needs no flip: it is negative inside a surface turned
    inside out, which it therefore does not count as inside.

    Examples
    --------
    >>> import trimesh
    >>> s = trimesh.creation.icosphere(3)
    >>> q = signed_distance(s.vertices, s.faces, np.array([[0, 0, 0.0], [2, 0, 0]]))
    >>> np.round(q.value, 2)
    array([-1.,  1.])
    >>> inverted = s.faces[:, ::-1]  # the same sphere, inside out
    >>> np.round(signed_distance(s.vertices, inverted, np.array([[0, 0, 0.0]]), oriented=True).value, 2)
    array([1.])
    """
    sign = resolve_sign(F, sign)
    scene = _scene(V, F) if sign == "raycast" else None
    cp = closest_points(V, F, Q, scene=scene)
    if sign == "unsigned":
        sgn = np.ones(len(Q))
    else:
        sgn = np.where(inside(V, F, Q, sign, scene=scene, samples=samples), -1.0, 1.0)
    if oriented and sign == "raycast" and signed_volume(V, F) < 0:
        sgn = -sgn  # inside out: the parity's inside is the surface's outside
    diff = Q - cp.points
    with np.errstate(divide="ignore", invalid="ignore"):
        normal = sgn[:, None] * diff / cp.distance[:, None]
    zero = cp.distance <= 1e-300
    if zero.any():
        tri = V[F[cp.faces[zero]]]
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        normal[zero] = fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    return SignedDistanceQuery(value=sgn * cp.distance, normal=normal, closest=cp)
