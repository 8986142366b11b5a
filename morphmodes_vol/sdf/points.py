"""The target SDF of an oriented point cloud (a scan), two ways.

- ``"winding"``: directly. The magnitude is the distance to the nearest point's tangent
  disc, ``max(|(q - p) . n|, |q - p| - r_p)`` (``r_p`` the radius of the point's share of
  the surface), so the field is flat along the surface between samples, not bumpy; the sign
  is the fast winding number of the oriented points (Barill et al. 2018, "Fast Winding
  Numbers for Soups and Clouds", libigl): inside where it exceeds 1/2. The winding number
  sums every point's solid angle, so a few noisy or missing points do not flip it: no holes
  or bubbles in the field.
- ``"poisson"``: screened Poisson reconstruction (Kazhdan and Hoppe 2013, Open3D) of a
  surface, trimmed where no point is near it (the reconstruction closes every hole of a
  partial scan with an invented surface) and rid of the specks that noise leaves beside it,
  then the mesh's own SDF. The mesh also serves the rest of the registration (rigid ICP,
  descriptors, correspondences).

Sign convention: negative inside.
"""

from __future__ import annotations

import logging
import typing
from typing import Literal

import numpy as np

from ..errors import PointCloudError
from .grid import Grid
from .target import DenseTargetSDF

__all__ = ["PointSDFMethod", "POINT_SDF_METHODS", "points_signed_distance", "poisson_surface", "poisson_depth",
           "points_target_sdf"]

log = logging.getLogger(__name__)

PointSDFMethod = Literal["winding", "poisson"]
POINT_SDF_METHODS = typing.get_args(PointSDFMethod)
_CHUNK = 1 << 18
_SCALE = 1.1  # Open3D's Poisson octree: the points' bounding cube enlarged this many times


def points_signed_distance(P: np.ndarray, N: np.ndarray, A: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Signed distance of the oriented points at ``Q (m, 3)``, ``(m,)`` (module docstring).

    Parameters
    ----------
    P, N : (k, 3) float
        Points and unit outward normals.
    A : (k,) float
        Each point's share of the surface (:func:`morphmodes_vol.pointcloud.point_areas`).
    Q : (m, 3) float

    Examples
    --------
    >>> from morphmodes_vol.primitives import icosphere
    >>> from morphmodes_vol.pointcloud import point_areas
    >>> V, _ = icosphere(4)
    >>> d = points_signed_distance(V, V, point_areas(V), np.array([[0, 0, 0.0], [0, 0, 2.0]]))
    >>> np.round(d, 2)
    array([-1.,  1.])
    """
    import igl
    from scipy.spatial import cKDTree

    P, N, A = (np.ascontiguousarray(a, dtype=np.float64) for a in (P, N, A))
    Q = np.ascontiguousarray(Q, dtype=np.float64)
    radius = np.sqrt(A / np.pi)
    tree = cKDTree(P)
    out = np.empty(len(Q))
    for start in range(0, len(Q), _CHUNK):
        q = Q[start:start + _CHUNK]
        d, i = tree.query(q)
        plane = np.abs(np.einsum("ij,ij->i", q - P[i], N[i]))
        magnitude = np.maximum(plane, d - radius[i])
        wn = igl.fast_winding_number(P, N, A, q)
        out[start:start + len(q)] = np.where(wn > 0.5, -magnitude, magnitude)
    return out


def poisson_surface(P: np.ndarray, N: np.ndarray, depth: int = 8, reach: float = 2.0, speck: float = 4.0,
                    decimate: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Screened Poisson reconstruction of the oriented points (Open3D; an octree of depth
    ``depth``, ``2^depth`` cells along its cube's side), trimmed: the vertices farther from
    every point than ``reach`` times the spacing of the points there (twice the radius of the
    nearest point's share of the surface) are removed, with their triangles, so that what the
    reconstruction invents over holes and beyond a partial scan is gone. Then the specks go:
    the pieces (triangles connected through their edges) whose bounding box spans at most
    ``speck`` cells of the octree along every axis. Noise leaves such closed bubbles of a few
    triangles beside the surface, which the grid cannot resolve while the surface's
    descriptors would see them (decision 0025). Last, quadric decimation (Garland and
    Heckbert 1997, Open3D) leaves ``1/decimate`` of the triangles: the surface of the finer
    octree, which follows the points closer, at the size of one level coarser (decision
    0026). The same points give the same surface, bit for bit. Returns ``V (n, 3), F (f, 3)``.

    Raises
    ------
    PointCloudError
        When the reconstruction leaves no triangle.
    """
    import open3d as o3d
    from scipy.spatial import cKDTree

    from ..pointcloud import point_areas

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    pcd.normals = o3d.utility.Vector3dVector(N)
    # one thread: with several, Open3D orders the vertices and rounds them differently from
    # run to run, and the registration onto the same points differed (0.38-0.43); one
    # thread is bitwise repeatable and no slower here (1.3 s against 1.5 s at depth 8)
    mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=int(depth), scale=_SCALE,
                                                                       n_threads=1)
    V = np.asarray(mesh.vertices, dtype=np.float64)
    spacing = 2 * np.sqrt(point_areas(P) / np.pi)
    d, i = cKDTree(P).query(V)
    mesh.remove_vertices_by_mask(d > reach * spacing[i])
    cell = _SCALE * np.ptp(P, axis=0).max() / 2 ** int(depth)
    mesh.remove_triangles_by_mask(_specks(np.asarray(mesh.vertices), np.asarray(mesh.triangles), speck * cell))
    mesh.remove_unreferenced_vertices()
    if decimate > 1:
        mesh = mesh.simplify_quadric_decimation(len(mesh.triangles) // int(decimate))
        mesh.remove_unreferenced_vertices()
    V, F = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles, dtype=np.int64)
    if len(F) == 0:
        raise PointCloudError("the Poisson reconstruction of the points left no surface")
    return V, F


def _specks(V: np.ndarray, F: np.ndarray, size: float) -> np.ndarray:
    """``(f,)`` bool: the triangles of the pieces (connected through edges) whose bounding box
    spans at most ``size`` along every axis."""
    import trimesh

    if len(F) == 0:
        return np.zeros(0, dtype=bool)
    labels = trimesh.graph.connected_component_labels(trimesh.graph.face_adjacency(F), node_count=len(F))
    corners = V[F]  # (f, 3, 3)
    lo = np.full((labels.max() + 1, 3), np.inf)
    hi = np.full((labels.max() + 1, 3), -np.inf)
    np.minimum.at(lo, labels, corners.min(axis=1))
    np.maximum.at(hi, labels, corners.max(axis=1))
    return ((hi - lo).max(axis=1) <= size)[labels]


def poisson_depth(grid_nodes: int) -> int:
    """The octree depth whose cells are a quarter of the spacing of a grid of ``grid_nodes``
    nodes along the box's longest side; :func:`poisson_surface` decimates its surface to what
    an octree of half the grid's spacing gives (decision 0026)."""
    return int(np.ceil(np.log2(4 * max(int(grid_nodes), 2))))


def points_target_sdf(P: np.ndarray, N: np.ndarray, grid: Grid, method: PointSDFMethod = "winding"
                      ) -> DenseTargetSDF:
    """The target SDF of the oriented points on the nodes of ``grid`` (``method`` of the
    module docstring); ``"poisson"`` through :func:`poisson_surface` and the mesh's SDF."""
    from ..pointcloud import point_areas

    if method == "winding":
        return DenseTargetSDF(grid, points_signed_distance(P, N, point_areas(P), grid.points()).reshape(grid.shape))
    if method == "poisson":
        V, F = poisson_surface(P, N, poisson_depth(max(grid.shape)))
        return DenseTargetSDF.from_mesh(V, F, grid, sign="winding")
    raise ValueError(f"method {method!r}: expected one of {POINT_SDF_METHODS}")
