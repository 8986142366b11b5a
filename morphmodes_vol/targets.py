"""Targets as the registration takes them: a mesh, an SDF (file or object) or a point cloud
(a scan, turned into a surface or a field first)."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .errors import OptionError
from .options import RegistrationOptions
from .pointcloud import PointCloud, as_point_cloud, is_point_cloud_file, load_point_cloud, oriented_normals
from .sdf import Grid, TargetSDF, build_target_sdf, is_target_sdf_path, load_target_sdf
from .sdf.points import points_target_sdf, poisson_depth, poisson_surface
from .sdf.target import TARGET_SDF_SUFFIXES, DenseTargetSDF, target_sdf_backend

if TYPE_CHECKING:
    from .register import Registration

__all__ = ["scan_target", "as_target_sdf", "save_target_sdf"]

log = logging.getLogger(__name__)


def scan_target(target, options: RegistrationOptions | None = None):
    """A point-cloud target (a file of :data:`~morphmodes_vol.pointcloud.POINT_EXTENSIONS`
    without faces, or a :class:`~morphmodes_vol.pointcloud.PointCloud`) as what the
    registration takes (``options.point_sdf``): its SDF on a grid over its padded box, in its
    own frame (``"winding"``), or its Poisson surface as a mesh ``(V, F)`` (``"poisson"``); any
    other target as it is.

    Raises
    ------
    PointCloudError
        A point cloud that cannot be read, fails :func:`~morphmodes_vol.pointcloud.as_point_cloud`
        or has no normals that can be estimated.
    """
    options = options or RegistrationOptions()
    if is_point_cloud_file(target):
        cloud = load_point_cloud(target)
    elif isinstance(target, PointCloud):
        cloud = as_point_cloud(target)
    else:
        return target
    t = time.perf_counter()
    normals = oriented_normals(cloud)
    if options.point_sdf == "poisson":
        V, F = poisson_surface(cloud.points, normals, poisson_depth(options.resolved_target_grid))
        log.info("target: Poisson surface of %d points, %d triangles (%.2f s)", len(cloud.points), len(F),
                 time.perf_counter() - t)
        return V, F
    P = cloud.points
    lo, hi = P.min(axis=0), P.max(axis=0)
    grid = Grid.covering(lo, hi, options.resolved_target_grid, options.padding * float(np.linalg.norm(hi - lo)))
    sdf = points_target_sdf(P, normals, grid, "winding")
    sdf.extrapolate = True  # a source beyond the scan's box: the distance to the box is added
    log.info("target: SDF of %d oriented points on %s nodes (%.2f s)", len(P), grid.shape, time.perf_counter() - t)
    return sdf


def as_target_sdf(target, options: RegistrationOptions) -> TargetSDF | None:
    """The target as a loaded SDF, or ``None`` when it is a mesh."""
    if is_target_sdf_path(target):
        if options.target_backend != "dense":
            log.info("target %s is an SDF file: its type decides the backend", target)
        return load_target_sdf(target, sign=options.target_sign)
    if hasattr(target, "sample") and hasattr(target, "surface_bounds"):
        return target
    return None


def save_target_sdf(reg: "Registration", path) -> Path:
    """Write the target's SDF to ``path`` (``.npz``: dense grid, ``.vdb``: OpenVDB level
    set) in the target's original frame, so that ``register(source, path)`` registers onto
    the same target. Returns the path.

    ``target_sdf`` itself is in the pair's normalized frame when the target is a mesh (and
    in the target's own frame for a pipeline's cached field): saved as it is, its target
    would sit at another place and scale. A dense grid built here is moved to the original
    frame exactly (nodes mapped back, spacing and values divided by the normalization's
    scale); an OpenVDB level set, or a pipeline's field, is rebuilt from the target mesh on
    the same lattice mapped back; a target given as an SDF is written as it was read, to a
    file of its own kind.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from morphmodes_vol.primitives import capsule
    >>> from morphmodes_vol import Registration, RegistrationOptions
    >>> from morphmodes_vol.sdf import load_target_sdf
    >>> V, F = capsule(count=(8, 8))
    >>> reg = Registration((V, F), (V * 3.0 + 5.0, F), RegistrationOptions(grid=16, modes=2))
    >>> path = save_target_sdf(reg, pathlib.Path(tempfile.mkdtemp()) / "target.npz")
    >>> lo, hi = load_target_sdf(path).surface_bounds()  # the target's box, [4.25, 5.75] x ... x [2.75, 7.25]
    >>> np.round(lo, 1).tolist(), np.round(hi, 1).tolist()
    ([4.3, 4.3, 2.8], [5.7, 5.7, 7.2])
    """
    path = Path(path)
    backend = target_sdf_backend(path)
    sdf = reg.target_sdf
    if reg.target_is_sdf:  # read from a file, in the target's original frame already
        kind = "dense" if isinstance(sdf, DenseTargetSDF) else "vdb"
        if kind != backend:
            suffix = next(s for s, b in TARGET_SDF_SUFFIXES.items() if b == kind)
            raise OptionError(f"{path}: the target was given as a {kind} SDF; write it to a "
                              f"{suffix} file")
        sdf.save(path)
        return path
    n, g, o = reg.normalization, reg.target_grid, reg.options
    grid = Grid(origin=n.undo(g.origin[None])[0], spacing=g.spacing / n.scale, shape=g.shape)
    if backend == "dense" and isinstance(sdf, DenseTargetSDF):
        out = DenseTargetSDF(grid, sdf.values / n.scale)
    else:
        log.info("target SDF: rebuilt in the target's frame for %s", path)
        out = build_target_sdf(reg.target_vertices, reg.target_sdf_faces, grid, backend,
                               o.target_sign, o.vdb_half_width)
    out.save(path)
    return path
