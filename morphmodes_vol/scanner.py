"""Virtual range scans of a mesh, as a depth camera makes them.

Rays from a pinhole camera (Open3D ``RaycastingScene.cast_rays``) looking at the mesh's
centre from each view direction; a hit gives a point and the surface normal turned to the
camera. As a scanner's, the points have depth-dependent noise along the ray (``sigma =
noise * diagonal * (depth / diagonal)^2``, the triangulation error of structured light and
stereo), and the grazing hits drop out (a hit is kept with probability ``(cos a - c) / (1 -
c)`` above the grazing cosine ``c``, ``a`` the angle between the ray and the normal). A scan
is written as oriented points, or as the range image's mesh: two triangles per square of four
neighbouring hits whose depths agree (no triangle across a depth jump).
:func:`virtual_scan` returns every view's; ``scripts/virtual_scan.py`` writes them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .mesh import validate_mesh

__all__ = ["RangeScan", "virtual_scan", "view_directions"]


@dataclass(frozen=True)
class RangeScan:
    """One view: ``points (k, 3)``, unit ``normals (k, 3)`` turned to the camera, the range
    image's ``faces (f, 3)`` over the points, and the camera's ``eye (3,)``."""

    points: np.ndarray
    normals: np.ndarray
    faces: np.ndarray
    eye: np.ndarray


def view_directions(count: int, first=None) -> np.ndarray:
    """``count`` unit directions the camera looks from: the first (default: the side view of
    :func:`~morphmodes_vol.variants.half_view_direction`, given by the caller) and the
    others turned about the vertical ``y`` axis by equal angles, ``(count, 3)``."""
    d = np.array([1.0, 0.0, 0.0] if first is None else first, dtype=np.float64)
    d /= np.linalg.norm(d)
    out = []
    for k in range(count):
        a = 2 * np.pi * k / count
        c, s = np.cos(a), np.sin(a)
        out.append([c * d[0] + s * d[2], d[1], -s * d[0] + c * d[2]])
    return np.array(out)


def virtual_scan(V, F, directions, resolution: tuple[int, int] = (320, 240), distance: float = 2.0,
                 noise: float = 1e-3, grazing: float = 0.1, seed: int = 0,
                 depth_jump: float = 3.0) -> list[RangeScan]:
    """Range scans of the mesh ``(V, F)`` from ``directions (v, 3)`` (module docstring).

    Parameters
    ----------
    V : (n, 3) float
    F : (f, 3) int
    directions : (v, 3) float
        Where each camera is, seen from the mesh's centre.
    resolution : (int, int)
        Pixels of the range image, width and height.
    distance : float
        The camera's distance from the centre, in bounding-box diagonals.
    noise : float
        Noise along the ray at a depth of one diagonal, relative to the diagonal (it grows
        with the square of the depth).
    grazing : float
        ``c``, the cosine under which every hit drops out.
    seed : int
    depth_jump : float
        Neighbouring hits are joined by a triangle only where their depths differ by less
        than this many pixel footprints.

    Returns
    -------
    list of RangeScan
        One per direction.

    Examples
    --------
    >>> from morphmodes_vol.primitives import icosphere
    >>> V, F = icosphere(3)
    >>> scan = virtual_scan(V, F, [[0, 0, 1.0]], resolution=(64, 48), noise=0.0)[0]
    >>> bool(np.abs(np.linalg.norm(scan.points, axis=1) - 1).max() < 0.01), bool(scan.points[:, 2].min() > -0.5)
    (True, True)
    """
    import open3d as o3d

    V, F = validate_mesh(V, F, "mesh")
    rng = np.random.default_rng(seed)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
    lo, hi = V.min(axis=0), V.max(axis=0)
    center, diagonal = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    width, height = resolution
    fov = float(np.degrees(2 * np.arctan(0.6 / distance)))  # the body's diagonal fills the view
    scans = []
    for d in np.asarray(directions, dtype=np.float64):
        d = d / np.linalg.norm(d)
        eye = center + distance * diagonal * d
        up = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            fov_deg=fov, center=center.tolist(), eye=eye.tolist(), up=up.tolist(),
            width_px=width, height_px=height)
        hit = scene.cast_rays(rays)
        R = rays.numpy().reshape(-1, 6).astype(np.float64)
        t = hit["t_hit"].numpy().reshape(-1).astype(np.float64)
        n = hit["primitive_normals"].numpy().reshape(-1, 3).astype(np.float64)
        direction = R[:, 3:] / np.linalg.norm(R[:, 3:], axis=1, keepdims=True)
        t = t * np.linalg.norm(R[:, 3:], axis=1)  # t_hit is in units of the ray's direction
        found = np.isfinite(t)
        n = np.where((np.einsum("ij,ij->i", n, direction) > 0)[:, None], -n, n)  # to the camera
        cos = -np.einsum("ij,ij->i", n, direction)
        keep = found & (rng.random(len(t)) < (cos - grazing) / (1 - grazing))
        t = np.where(found, t, 0.0)
        depth = t + rng.normal(size=len(t)) * noise * diagonal * (t / diagonal) ** 2
        points = R[:, :3] + depth[:, None] * direction
        footprint = depth_jump * (depth[keep].max() if keep.any() else 0.0) * 2 * np.tan(np.radians(fov) / 2) / height
        P, N = points[keep], n[keep]
        faces = _range_faces(keep, depth, (height, width), footprint, P, N)
        scans.append(RangeScan(points=P, normals=N, faces=faces, eye=eye))
    return scans


def _range_faces(keep: np.ndarray, depth: np.ndarray, shape: tuple, footprint: float, P: np.ndarray,
                 N: np.ndarray) -> np.ndarray:
    """The range image's triangles ``(f, 3)`` over the kept pixels' points ``P`` (normals
    ``N``): squares of four kept pixels whose depths agree within ``footprint``, two
    triangles each, wound with their normals towards the camera."""
    index = np.full(len(depth), -1, dtype=np.int64)
    index[keep] = np.arange(int(keep.sum()))
    grid = index.reshape(shape)
    z = np.where(keep, depth, np.nan).reshape(shape)
    a, b, c, e = grid[:-1, :-1], grid[:-1, 1:], grid[1:, :-1], grid[1:, 1:]
    corners = np.stack([z[:-1, :-1], z[:-1, 1:], z[1:, :-1], z[1:, 1:]])
    square = (a >= 0) & (b >= 0) & (c >= 0) & (e >= 0)  # four hits: no NaN among their depths
    spread = np.where(square, np.max(np.nan_to_num(corners), axis=0) - np.min(np.nan_to_num(corners), axis=0), np.inf)
    square &= spread < footprint
    faces = np.concatenate([np.stack([a[square], c[square], b[square]], axis=1),
                            np.stack([b[square], c[square], e[square]], axis=1)]).astype(np.int64)
    if len(faces):
        fn = np.cross(P[faces[:, 1]] - P[faces[:, 0]], P[faces[:, 2]] - P[faces[:, 0]])
        if np.einsum("ij,ij->i", fn, N[faces[:, 0]]).sum() < 0:
            faces = faces[:, [0, 2, 1]]
    return faces
