"""Point-cloud targets: what a scanner delivers, read, checked and given oriented normals.

A target may be a point cloud (PLY without faces, PCD, XYZ, XYZN, PTS: Open3D reads them),
with or without normals. :func:`load_point_cloud` reads one, :func:`as_point_cloud` checks
points given in memory (the one validator: too few, NaN or infinite, duplicates only, all on
a plane or a line, unusable normals, each one line naming the file), and
:func:`oriented_normals` estimates and orients normals where there are none (Open3D
``estimate_normals`` and ``orient_normals_consistent_tangent_plane``), outward (the signed
volume ``sum_i a_i p_i . n_i / 3`` of the divergence theorem is positive). The target SDF
built from oriented points is :func:`morphmodes_vol.sdf.points.points_target_sdf`.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import PointCloudError

__all__ = ["PointCloud", "POINT_EXTENSIONS", "MIN_POINTS", "is_point_cloud_file", "load_point_cloud",
           "as_point_cloud", "oriented_normals", "point_areas"]

log = logging.getLogger(__name__)

POINT_EXTENSIONS = ("ply", "pcd", "xyz", "xyzn", "xyzrgb", "pts")
"""Point-cloud files read (a PLY only when it has no faces)."""
MIN_POINTS = 100
"""Fewest distinct points accepted: a surface, not a handful of samples."""
_NEIGHBOURS = 20  # normals: the plane fitted to this many nearest points
_ORIENT_NEIGHBOURS = 12  # and the graph that propagates their orientation
_ORIENT_POINTS = 40_000  # that graph spans at most this many points; the others follow the nearest


@dataclass(frozen=True)
class PointCloud:
    """Points ``(k, 3) float64`` and, when known, their unit normals ``(k, 3) float64``
    (pointing out of the scanned body), in the scan's frame."""

    points: np.ndarray
    normals: np.ndarray | None = None


def _ply_has_faces(path: Path) -> bool:
    """Whether a PLY file's header declares a non-empty face element."""
    with open(path, "rb") as fh:
        for raw in fh:
            line = raw.decode("ascii", "replace").strip()
            if line.startswith("element face"):
                parts = line.split()
                return len(parts) >= 3 and parts[2] != "0"
            if line == "end_header":
                return False
    return False


def is_point_cloud_file(path) -> bool:
    """Whether ``path`` is a point-cloud file: one of :data:`POINT_EXTENSIONS`, a PLY only
    without faces."""
    if not isinstance(path, (str, os.PathLike)):
        return False
    path = Path(path)
    ext = path.suffix.lower().lstrip(".")
    if ext not in POINT_EXTENSIONS:
        return False
    return ext != "ply" or (path.is_file() and not _ply_has_faces(path))


def load_point_cloud(path) -> PointCloud:
    """Read a point cloud (:data:`POINT_EXTENSIONS`) with Open3D, normals kept when the file
    has them, and check it (:func:`as_point_cloud`).

    Raises
    ------
    PointCloudError
        Missing or unreadable file, or points that fail :func:`as_point_cloud`.
    """
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise PointCloudError(f"{path}: no such file")
    ext = path.suffix.lower().lstrip(".")
    # Open3D's XYZ readers are picked by the suffix; PTS files are read as XYZ
    fmt = {"pts": "xyz"}.get(ext, "auto")
    try:
        pcd = o3d.io.read_point_cloud(str(path), format=fmt, remove_nan_points=False,
                                      remove_infinite_points=False)
    except Exception as exc:  # Open3D raises RuntimeError for unreadable files
        raise PointCloudError(f"{path}: cannot be read as a point cloud ({exc})") from None
    P = np.asarray(pcd.points, dtype=np.float64)
    N = np.asarray(pcd.normals, dtype=np.float64) if pcd.has_normals() else None
    return as_point_cloud(PointCloud(P, N), str(path))


def as_point_cloud(cloud, name: str = "target") -> PointCloud:
    """Validated copies of a point cloud (:class:`PointCloud`, or ``points (k, 3)``, or
    ``(points, normals)``).

    Raises
    ------
    PointCloudError
        Fewer than :data:`MIN_POINTS` points, NaN or infinite coordinates, fewer than
        :data:`MIN_POINTS` distinct points (duplicates only), all points on a plane or a line,
        normals of the wrong shape, not finite or of zero length.

    Examples
    --------
    >>> P = np.random.default_rng(0).normal(size=(500, 3))
    >>> as_point_cloud(P).points.shape
    (500, 3)
    >>> as_point_cloud(P * [1, 1, 0])
    Traceback (most recent call last):
    ...
    morphmodes_vol.errors.PointCloudError: target: all 500 points lie on a plane (a point cloud of a surface spans 3D)
    """
    if isinstance(cloud, PointCloud):
        P, N = cloud.points, cloud.normals
    elif isinstance(cloud, tuple) and len(cloud) == 2:
        P, N = cloud
    else:
        P, N = cloud, None
    try:
        P = np.array(P, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PointCloudError(f"{name}: points are not a numeric array ({exc})") from None
    if P.ndim != 2 or P.shape[1] != 3:
        raise PointCloudError(f"{name}: points must be (k, 3), got shape {P.shape}")
    bad = ~np.isfinite(P).all(axis=1)
    if bad.any():
        raise PointCloudError(f"{name}: {int(bad.sum())} points have NaN or infinite coordinates "
                              f"(first: point {int(np.flatnonzero(bad)[0])})")
    if len(P) < MIN_POINTS:
        raise PointCloudError(f"{name}: {len(P)} points, fewer than the {MIN_POINTS} a surface needs")
    distinct = len(np.unique(P, axis=0))
    if distinct < MIN_POINTS:
        raise PointCloudError(f"{name}: only {distinct} distinct points among {len(P)} (duplicates), "
                              f"fewer than the {MIN_POINTS} a surface needs")
    s = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    if s[1] <= 1e-9 * s[0]:
        raise PointCloudError(f"{name}: all {len(P)} points lie on a line (a point cloud of a surface spans 3D)")
    if s[2] <= 1e-9 * s[0]:
        raise PointCloudError(f"{name}: all {len(P)} points lie on a plane (a point cloud of a surface spans 3D)")
    if N is not None:
        N = np.array(N, dtype=np.float64)
        if N.size == 0:
            N = None
        elif N.shape != P.shape:
            raise PointCloudError(f"{name}: normals must be {P.shape} like the points, got {N.shape}")
        else:
            length = np.linalg.norm(N, axis=1)
            bad = ~np.isfinite(length) | (length <= 0)
            if bad.any():
                raise PointCloudError(f"{name}: {int(bad.sum())} normals are NaN, infinite or zero "
                                      f"(first: point {int(np.flatnonzero(bad)[0])})")
            N = N / length[:, None]
    return PointCloud(P, N)


def point_areas(P: np.ndarray, k: int = 8) -> np.ndarray:
    """The share of the surface each point stands for, ``(k,)``: ``pi r_k^2 / k`` with ``r_k``
    the distance to its ``k``-th nearest point (uniform density ``rho`` puts ``k`` points
    within ``sqrt(k / (pi rho))``), so the shares integrate the surface whatever the density."""
    from scipy.spatial import cKDTree

    k = min(k, len(P) - 1)
    d, _ = cKDTree(P).query(P, k + 1)
    return np.pi * d[:, k] ** 2 / k


def _signed_volume(P: np.ndarray, N: np.ndarray) -> float:
    return float(np.sum(point_areas(P) * np.einsum("ij,ij->i", P - P.mean(axis=0), N)) / 3.0)


def oriented_normals(cloud: PointCloud, name: str = "target") -> np.ndarray:
    """Unit normals of ``cloud`` pointing out of the body, ``(k, 3)``: its own when it has
    them, else estimated by Open3D (a plane fitted to the nearest points, then a consistent
    orientation propagated over a graph of neighbours) and turned outward as a whole (the
    divergence theorem's signed volume positive). The graph spans at most 40k points drawn
    evenly (seeded); a denser scan's other points take the side of their nearest one.

    Raises
    ------
    PointCloudError
        When the normals cannot be estimated or oriented (Open3D fails, or gives NaN).
    """
    if cloud.normals is not None:
        return cloud.normals
    import open3d as o3d
    from scipy.spatial import cKDTree

    P = cloud.points
    # the orientation graph spans an even subset: the graph costs seconds per 10^5 points,
    # and a denser one orients no better (a 300k-point scan's surface is as close either way)
    sub = (np.arange(len(P)) if len(P) <= _ORIENT_POINTS
           else np.sort(np.random.default_rng(0).choice(len(P), _ORIENT_POINTS, replace=False)))
    tree = cKDTree(P)
    # a neighbourhood on a line has no normal: its plane's second spread is zero
    _, idx = tree.query(P[sub], min(_NEIGHBOURS, len(P)))
    local = P[idx] - P[idx].mean(axis=1, keepdims=True)
    spread = np.linalg.eigvalsh(np.einsum("kni,knj->kij", local, local))  # ascending
    lines = spread[:, 1] <= 1e-12 * spread[:, 2]
    if lines.mean() > 0.5:
        raise PointCloudError(f"{name}: normals cannot be estimated: the nearest points of "
                              f"{lines.mean():.0%} of the points lie on a line; give the scan with normals")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    try:
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=_NEIGHBOURS))
        N = np.asarray(pcd.normals, dtype=np.float64)
        graph = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P[sub]))
        graph.normals = o3d.utility.Vector3dVector(N[sub])
        graph.orient_normals_consistent_tangent_plane(_ORIENT_NEIGHBOURS)
    except RuntimeError as exc:
        raise PointCloudError(f"{name}: normals cannot be estimated and oriented ({exc})") from None
    # every point takes the side of its nearest oriented point (itself, when in the subset)
    oriented = np.asarray(graph.normals, dtype=np.float64)
    nearest = cKDTree(P[sub]).query(P)[1] if len(sub) < len(P) else sub
    N = np.where((np.einsum("ij,ij->i", N, oriented[nearest]) < 0)[:, None], -N, N)
    length = np.linalg.norm(N, axis=1)
    if not (np.isfinite(length).all() and (length > 0).all()):
        raise PointCloudError(f"{name}: normals cannot be estimated: some are NaN or zero "
                              "(points too sparse or degenerate); give the scan with normals")
    N = N / length[:, None]
    if _signed_volume(cloud.points, N) < 0:
        N = -N
    log.info("%s: normals of %d points estimated and oriented", name, len(N))
    return N
