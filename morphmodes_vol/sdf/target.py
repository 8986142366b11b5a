"""The target SDF: computed once, sampled at the quadrature points.

One interface, :class:`TargetSDF` (``sample(points) -> (k,)``, ``surface_bounds()``,
``nbytes``, ``save(path)``), two backends:

- ``"dense"`` (default): :class:`DenseTargetSDF`, a regular grid of exact signed distances,
  trilinear interpolation; memory ``8 * nodes`` bytes (float64).
- ``"vdb"``: :class:`~morphmodes_vol.sdf.vdb.VDBTargetSDF`, a narrow-band OpenVDB level set
  with the exact distance of the surface outside the band (needs ``pyopenvdb`` under NumPy
  1.x, see :func:`~morphmodes_vol.sdf.vdb.check_openvdb`).

Sign convention: negative inside. The inside test of the target is selectable
(``target_sign``): ``"winding"`` (default, the generalized winding number > 1/2, libigl's
fast winding number) stays right behind the holes of an open target, where ``"raycast"``
(Open3D ray parity) is wrong in a shadow behind each hole; docs/target_sdf.md measures both.

:func:`build_target_sdf` builds either backend from a mesh, :func:`load_target_sdf` reads a
``.npz`` (dense) or ``.vdb`` (level set) file, ``sdf.save(path)`` writes one.
"""

from __future__ import annotations

import io
import logging
import os
import typing
from pathlib import Path
from typing import Literal, Protocol, runtime_checkable

import numpy as np

from ..errors import OptionError, TargetSDFLoadError
from .grid import Grid, trilinear_sample
from .source import SignMethod, signed_distance

__all__ = [
    "TargetSDF",
    "TargetBackend",
    "TARGET_BACKENDS",
    "TARGET_SDF_SUFFIXES",
    "DenseTargetSDF",
    "build_target_sdf",
    "is_target_sdf_path",
    "load_target_sdf",
    "target_sdf_backend",
]

log = logging.getLogger(__name__)

TargetBackend = Literal["dense", "vdb"]
TARGET_BACKENDS = typing.get_args(TargetBackend)
# File suffixes read by load_target_sdf, and the backend each one holds.
TARGET_SDF_SUFFIXES = {".npz": "dense", ".vdb": "vdb"}
_NPZ_FORMAT = "morphmodes-vol dense target sdf 1"

# Query the BVH in chunks to bound the memory of Open3D's result tensors.
_CHUNK = 1 << 20


@runtime_checkable
class TargetSDF(Protocol):
    """What the registration needs of a target SDF (negative inside)."""

    def sample(self, points: np.ndarray) -> np.ndarray:
        """Signed distance at ``points (k, 3)``, returns ``(k,)`` float64."""

    def surface_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Corners ``lo, hi (3,)`` of the bounding box of the zero level set."""

    def save(self, path) -> None:
        """Write the SDF to a file :func:`load_target_sdf` reads."""

    @property
    def nbytes(self) -> int:
        """Memory held by the SDF, in bytes."""


class DenseTargetSDF:
    """Signed distance of the target on a regular grid (negative inside).

    Parameters
    ----------
    grid : Grid
        The nodes.
    values : (nx, ny, nz) float
        Signed distance at the nodes.

    Examples
    --------
    >>> import trimesh
    >>> s = trimesh.creation.icosphere(3)
    >>> sdf = DenseTargetSDF.from_mesh(s.vertices, s.faces, Grid.covering([-1.2] * 3, [1.2] * 3, 25))
    >>> bool(abs(sdf.sample(np.array([[0.0, 0.0, 0.0]]))[0] + 1) < 0.02)
    True
    """

    def __init__(self, grid: Grid, values: np.ndarray, extrapolate: bool = False):
        self.grid = grid
        self.values = np.asarray(values, dtype=np.float64).reshape(grid.shape)
        # outside the box: False clamps to the boundary (a registration's own grid covers its
        # quadrature box); True, for grids read from files, adds the distance to the box
        self.extrapolate = bool(extrapolate)

    @classmethod
    def from_mesh(cls, V, F, grid: Grid, sign: SignMethod = "winding") -> "DenseTargetSDF":
        """Evaluate the signed distance of ``(V, F)`` at every node of ``grid``.

        ``sign="winding"`` (default) decides inside by the generalized winding number, which
        stays correct behind holes of an open target; ``"raycast"`` uses ray parity.
        """
        P = grid.points()
        values = np.empty(P.shape[0])
        for start in range(0, P.shape[0], _CHUNK):
            chunk = P[start : start + _CHUNK]
            values[start : start + len(chunk)] = signed_distance(V, F, chunk, sign=sign).value
        log.debug("target SDF: %s nodes, spacing %.4g", grid.shape, grid.spacing)
        return cls(grid, values.reshape(grid.shape))

    @classmethod
    def load(cls, path) -> "DenseTargetSDF":
        """Read a ``.npz`` written by :meth:`save`."""
        path = Path(path)
        if not path.is_file():
            raise TargetSDFLoadError(f"{path}: no such file")
        try:
            with np.load(path, allow_pickle=False) as z:
                fmt = str(z["format"]) if "format" in z else None
                if fmt != _NPZ_FORMAT:
                    raise TargetSDFLoadError(
                        f"{path}: not a dense target SDF (format {fmt!r}, expected "
                        f"{_NPZ_FORMAT!r}; write one with `morphmodes-vol sdf`)"
                    )
                origin = np.asarray(z["origin"], dtype=np.float64)
                spacing = float(z["spacing"])
                values = np.asarray(z["values"], dtype=np.float64)
        except TargetSDFLoadError:
            raise
        except Exception as exc:  # zipfile/pickle/KeyError on foreign or damaged files
            raise TargetSDFLoadError(f"{path}: cannot be read ({type(exc).__name__}: {exc})") from None
        if origin.shape != (3,) or values.ndim != 3 or min(values.shape) < 2 or not spacing > 0:
            raise TargetSDFLoadError(
                f"{path}: expected origin (3,), spacing > 0 and values (nx, ny, nz) with every "
                f"side >= 2; got {origin.shape}, {spacing}, {values.shape}"
            )
        if not np.isfinite(values).all():
            raise TargetSDFLoadError(f"{path}: values contain NaN or infinity")
        return cls(Grid(origin=origin, spacing=spacing, shape=values.shape), values, extrapolate=True)

    def save(self, path) -> None:
        """Write ``origin``, ``spacing`` and the values (as float32, half the size; the
        rounding, ~1e-7 relative, is far below the interpolation error) to ``.npz``, atomically."""
        from ..export import atomic_write_bytes

        buf = io.BytesIO()
        np.savez(buf, format=np.str_(_NPZ_FORMAT), origin=self.grid.origin,
                 spacing=np.float64(self.grid.spacing), values=self.values.astype(np.float32))
        atomic_write_bytes(path, buf.getvalue())

    def sample(self, points: np.ndarray) -> np.ndarray:
        """Trilinear interpolation at ``points (k, 3)``; returns ``(k,)``.

        Outside the grid's box: the value at the nearest point of the box, plus (when
        ``extrapolate``, as for a grid read by :meth:`load`, which need not cover the
        registration's box) the distance to that point, an upper bound of the true distance
        outside a surface the box contains.
        """
        values = trilinear_sample(self.values, self.grid, points)
        if self.extrapolate:
            values = values + self.grid.distance_outside(points)
        return values

    def surface_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounding box of the zero level set of the trilinear field along the grid edges
        (the linearly interpolated crossing on every edge the sign changes along)."""
        v = self.values
        points = []
        for axis in range(3):
            a = [slice(None)] * 3
            b = [slice(None)] * 3
            a[axis], b[axis] = slice(0, -1), slice(1, None)
            v0, v1 = v[tuple(a)], v[tuple(b)]
            change = (v0 < 0) != (v1 < 0)
            ijk = np.argwhere(change).astype(np.float64)
            ijk[:, axis] += v0[change] / (v0[change] - v1[change])
            points.append(ijk)
        ijk = np.concatenate(points)
        if ijk.shape[0] == 0:
            raise TargetSDFLoadError("the dense target SDF has no sign change: no surface in its box")
        return (self.grid.origin + self.grid.spacing * ijk.min(axis=0),
                self.grid.origin + self.grid.spacing * ijk.max(axis=0))

    @property
    def nbytes(self) -> int:
        return int(self.values.nbytes)


def build_target_sdf(V, F, grid: Grid, backend: TargetBackend = "dense",
                     sign: SignMethod = "winding", half_width: float = 3.0) -> TargetSDF:
    """The target SDF of the mesh ``(V, F)`` with the resolution of ``grid``.

    Parameters
    ----------
    V : (n, 3) float
    F : (m, 3) int
    grid : Grid
        ``"dense"``: the nodes. ``"vdb"``: its spacing and origin place the voxels on the same
        lattice (the band covers what it covers, whatever the grid's extent).
    backend : {"dense", "vdb"}
    sign : {"winding", "raycast"}
        Inside test (negative inside).
    half_width : float
        Band half width of the ``"vdb"`` backend, in voxels.

    Examples
    --------
    >>> import trimesh
    >>> s = trimesh.creation.icosphere(3)
    >>> sdf = build_target_sdf(s.vertices, s.faces, Grid.covering([-1.2] * 3, [1.2] * 3, 25))
    >>> type(sdf).__name__, isinstance(sdf, TargetSDF)
    ('DenseTargetSDF', True)
    """
    if backend == "dense":
        return DenseTargetSDF.from_mesh(V, F, grid, sign=sign)
    if backend == "vdb":
        from .vdb import VDBTargetSDF

        return VDBTargetSDF.from_mesh(V, F, grid.spacing, half_width=half_width, sign=sign,
                                      origin=grid.origin)
    raise OptionError(f"target backend {backend!r}: expected one of {TARGET_BACKENDS}")


def target_sdf_backend(path) -> TargetBackend:
    """The backend a target-SDF file at ``path`` holds, by its suffix (``.npz``: ``"dense"``,
    ``.vdb``: ``"vdb"``); :class:`OptionError` for another suffix (a file to write).

    Examples
    --------
    >>> target_sdf_backend("out/lion.VDB")
    'vdb'
    """
    backend = TARGET_SDF_SUFFIXES.get(Path(path).suffix.lower())
    if backend is None:
        raise OptionError(f"{path}: a target SDF file ends in one of {sorted(TARGET_SDF_SUFFIXES)} "
                          "(.npz: dense grid, .vdb: OpenVDB level set)")
    return backend


def is_target_sdf_path(target) -> bool:
    """Whether ``target`` is a path whose suffix :func:`load_target_sdf` reads."""
    return isinstance(target, (str, os.PathLike)) and Path(target).suffix.lower() in TARGET_SDF_SUFFIXES


def load_target_sdf(path, sign: SignMethod = "winding") -> TargetSDF:
    """Read a target SDF: ``.npz`` (dense, as :meth:`DenseTargetSDF.save` writes) or ``.vdb``
    (the first float level-set grid; ``sign`` is the inside test of its far field)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".npz":
        return DenseTargetSDF.load(path)
    if suffix == ".vdb":
        from .vdb import VDBTargetSDF

        return VDBTargetSDF.load(path, sign=sign)
    raise TargetSDFLoadError(
        f"{path}: unknown target-SDF file type {suffix!r}; expected one of {sorted(TARGET_SDF_SUFFIXES)}"
    )
