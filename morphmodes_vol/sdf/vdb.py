"""The ``vdb`` target backend: a narrow-band OpenVDB level set with an exact far field.

Inside the band (``|d| < half_width`` voxels, where OpenVDB stores voxels) the signed distance
is the trilinear interpolation of the voxel values, exactly as the dense backend interpolates
its nodes. Outside the band OpenVDB only knows ``+-background``; there :meth:`sample` falls
back to the exact signed distance of the surface mesh (the target mesh, or for a loaded
``.vdb`` file the grid's zero isosurface), signed by the same inside test. So the energy of
Eq. (3) sees the true distance everywhere, as with the dense backend, and the registration
results of the two backends stay close (``tests/test_target_sdf.py``). The far field costs
one closest-point query per sample point outside the band; :class:`Registration` samples the
target once, at the quadrature points.

Signs: OpenVDB's ``createLevelSetFromPolygons`` decides inside by flood fill, which leaks
through the holes of an open mesh. With ``sign="winding"`` (default) the sign of every band
voxel is recomputed from the generalized winding number (libigl), then the inactive tiles get
their sign by OpenVDB's ``signedFloodFill``; negative inside.

Debian's ``python3-openvdb`` (OpenVDB 10) is built against NumPy 1.x and crashes the process
under NumPy 2, so :func:`check_openvdb` refuses to use it there (``bash dev.sh vdb-env``
makes a working environment, ``.venv-vdb``).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import OpenVDBUnavailableError, OptionError, TargetSDFLoadError
from .grid import Grid, trilinear_sample
from .source import SignMethod, inside, signed_distance

__all__ = ["VDBTargetSDF", "check_openvdb"]

log = logging.getLogger(__name__)

_SETUP_HINT = "run `bash dev.sh vdb-env` (or `make vdb-env`) and use .venv-vdb/bin/python"
# Edge of the dense blocks copied out of the tree (a 65^3 float32 block is 1.1 MB).
_BLOCK = 64


def check_openvdb():
    """Import ``pyopenvdb`` only if it can work; return the module.

    Raises
    ------
    OpenVDBUnavailableError
        If NumPy is 2.x (Debian's OpenVDB 10 bindings are built against NumPy 1.x and crash
        the interpreter under NumPy 2) or the module is not importable.
    """
    major = int(np.__version__.split(".")[0])
    if major >= 2:
        raise OpenVDBUnavailableError(
            f"the vdb target backend needs NumPy 1.x (OpenVDB 10's Python bindings crash under "
            f"NumPy 2), but NumPy {np.__version__} is loaded; {_SETUP_HINT}"
        )
    try:
        import pyopenvdb
    except ImportError as exc:
        raise OpenVDBUnavailableError(
            f"the vdb target backend needs the pyopenvdb module ({exc}); {_SETUP_HINT}"
        ) from None
    return pyopenvdb


def _copy_block(grid, start: np.ndarray, shape) -> np.ndarray:
    """Dense float32 copy of the voxels ``start + [0, shape)`` (inactive ones: their tile value)."""
    block = np.empty(tuple(int(s) for s in shape), dtype=np.float32)
    grid.copyToArray(block, ijk=tuple(int(s) for s in start))
    return block


def _block_starts(lo: np.ndarray, hi: np.ndarray):
    """Corners of the ``_BLOCK^3`` blocks tiling the index box ``[lo, hi]`` (inclusive)."""
    axes = [np.arange(lo[d], hi[d] + 1, _BLOCK) for d in range(3)]
    for i in axes[0]:
        for j in axes[1]:
            for k in axes[2]:
                start = np.array([i, j, k])
                yield start, np.minimum(hi + 1 - start, _BLOCK)


class VDBTargetSDF:
    """Signed distance of the target as a narrow-band OpenVDB level set (negative inside).

    Parameters
    ----------
    grid : pyopenvdb.FloatGrid
        A level set with a linear transform: uniform voxel size, no rotation.
    surface_vertices : (n, 3) float
    surface_faces : (m, 3) int
        The surface whose exact distance is used outside the band.
    sign : {"winding", "raycast"}
        Inside test of that far field.

    Examples
    --------
    >>> import trimesh                                           # doctest: +SKIP
    >>> s = trimesh.creation.icosphere(3)                        # doctest: +SKIP
    >>> sdf = VDBTargetSDF.from_mesh(s.vertices, s.faces, 0.1)   # doctest: +SKIP
    >>> sdf.sample(np.array([[0.0, 0, 0], [0.0, 0, 0.95]]))      # doctest: +SKIP
    array([-1.  , -0.05])
    """

    def __init__(self, grid, surface_vertices, surface_faces, sign: SignMethod = "winding"):
        vdb = check_openvdb()
        xform = grid.transform
        if not xform.isLinear:
            raise TargetSDFLoadError("the level set has a non-linear (frustum) transform")
        origin = np.array(xform.indexToWorld((0, 0, 0)), dtype=np.float64)
        axes = np.array([xform.indexToWorld(tuple(float(c) for c in e)) for e in np.eye(3)]) - origin
        h = float(axes[0, 0])
        if h <= 0 or not np.allclose(axes, h * np.eye(3), rtol=1e-6, atol=1e-12 * abs(h)):
            raise TargetSDFLoadError(
                f"the level set's transform must be a uniform scale plus translation, got index "
                f"axes {axes.tolist()}"
            )
        if grid.gridClass != vdb.GridClass.LEVEL_SET:
            log.warning("grid %r is not marked as a level set (class %r); reading it as one",
                        grid.name, grid.gridClass)
        self.grid = grid
        self.origin = origin
        self.voxel_size = h
        self.background = float(grid.background)
        self.surface_vertices = np.ascontiguousarray(surface_vertices, dtype=np.float64)
        self.surface_faces = np.ascontiguousarray(surface_faces, dtype=np.int64)
        self.sign: SignMethod = sign
        lo, hi = grid.evalActiveVoxelBoundingBox()
        self._active_lo, self._active_hi = np.array(lo), np.array(hi)

    @classmethod
    def from_mesh(cls, V, F, voxel_size: float, half_width: float = 3.0,
                  sign: SignMethod = "winding", origin=(0.0, 0.0, 0.0)) -> "VDBTargetSDF":
        """Narrow-band level set of the mesh ``(V, F)``.

        Parameters
        ----------
        V : (n, 3) float
        F : (m, 3) int
        voxel_size : float
            Edge of a voxel; voxel ``(i, j, k)`` sits at ``origin + voxel_size * (i, j, k)``.
        half_width : float
            Band half width in voxels (OpenVDB's default is 3).
        sign : {"winding", "raycast"}
            ``"winding"`` recomputes the sign of every band voxel from the generalized
            winding number (robust to holes); ``"raycast"`` keeps OpenVDB's flood-fill sign.
        origin : (3,) float
            Position of voxel ``(0, 0, 0)``; :func:`~morphmodes_vol.sdf.build_target_sdf`
            passes the dense grid's origin, so the voxels sit on the dense backend's nodes.
        """
        vdb = check_openvdb()
        if not voxel_size > 0 or not half_width >= 1:
            raise OptionError(f"need voxel_size > 0 and half_width >= 1, got {voxel_size}, {half_width}")
        V = np.ascontiguousarray(V, dtype=np.float64)
        F = np.ascontiguousarray(F, dtype=np.int64)
        xform = vdb.createLinearTransform(voxelSize=float(voxel_size))
        xform.translate(tuple(float(c) for c in origin))
        grid = vdb.FloatGrid.createLevelSetFromPolygons(
            V.astype(np.float32), triangles=F.astype(np.int32), transform=xform,
            halfWidth=float(half_width),
        )
        grid.name = "surface"
        if sign == "winding":
            grid = _resign_band(vdb, grid, V, F)
        elif sign != "raycast":
            raise OptionError(f"sign method {sign!r}: expected one of ('winding', 'raycast')")
        log.debug("vdb target SDF: %d active voxels, %.1f MB", grid.activeVoxelCount(),
                  grid.memUsage() / 1e6)
        return cls(grid, V, F, sign=sign)

    @classmethod
    def load(cls, path, sign: SignMethod = "winding") -> "VDBTargetSDF":
        """Read the first float level-set grid of a ``.vdb`` file (as Houdini, Blender or
        :meth:`save` write it); the far field comes from its zero isosurface."""
        vdb = check_openvdb()
        path = Path(path)
        if not path.is_file():
            raise TargetSDFLoadError(f"{path}: no such file")
        try:
            grids, _ = vdb.readAll(str(path))
        except Exception as exc:  # OpenVDB raises IOError/RuntimeError/ValueError
            raise TargetSDFLoadError(f"{path}: cannot be read as a .vdb file ({exc})") from None
        floats = [g for g in grids if getattr(g, "valueTypeName", "") == "float"]
        level_sets = [g for g in floats if g.gridClass == vdb.GridClass.LEVEL_SET]
        if not floats:
            raise TargetSDFLoadError(
                f"{path}: holds no float grid (found {[type(g).__name__ for g in grids]})"
            )
        grid = (level_sets or floats)[0]
        if grid.activeVoxelCount() == 0:
            raise TargetSDFLoadError(f"{path}: grid {grid.name!r} has no active voxels")
        points, tris, quads = grid.convertToPolygons(isovalue=0.0, adaptivity=0.0)
        quads = np.asarray(quads, dtype=np.int64).reshape(-1, 4)
        F = np.concatenate([np.asarray(tris, dtype=np.int64).reshape(-1, 3),
                            quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
        if F.shape[0] == 0:
            raise TargetSDFLoadError(f"{path}: grid {grid.name!r} has no zero isosurface")
        # orient the isosurface outward (positive enclosed volume), as the winding-number
        # inside test expects; OpenVDB's orientation convention is not documented
        V = np.asarray(points, dtype=np.float64)
        tri = V[F]
        if np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() < 0:
            F = F[:, ::-1].copy()
        log.info("%s: grid %r, %d active voxels, voxel size %.4g, isosurface %d faces",
                 path, grid.name, grid.activeVoxelCount(), grid.transform.voxelSize()[0], F.shape[0])
        return cls(grid, V, F, sign=sign)

    def save(self, path) -> None:
        """Write the level set to a ``.vdb`` file atomically (temporary file, then rename)."""
        from ..export import atomic_path

        vdb = check_openvdb()
        with atomic_path(path, suffix=".vdb") as tmp:
            vdb.write(str(tmp), [self.grid])

    def sample(self, points: np.ndarray) -> np.ndarray:
        """Signed distance at ``points (k, 3)``; returns ``(k,)`` float64.

        Trilinear interpolation of the voxels where all eight corners lie in the band, the
        exact signed distance of the surface mesh elsewhere (see the module docstring).
        """
        points = np.asarray(points, dtype=np.float64)
        i0 = np.floor((points - self.origin) / self.voxel_size).astype(np.int64)
        out = np.empty(points.shape[0])
        band = np.zeros(points.shape[0], dtype=bool)
        near = np.all((i0 >= self._active_lo) & (i0 < self._active_hi), axis=1)
        idx = np.flatnonzero(near)
        if idx.size:
            keys, inverse = np.unique(i0[idx] // _BLOCK, axis=0, return_inverse=True)
            inverse = inverse.ravel()
            for b, key in enumerate(keys):
                sel = idx[inverse == b]
                start = key * _BLOCK
                block = _copy_block(self.grid, start, (_BLOCK + 1,) * 3)
                local = Grid(origin=self.origin + self.voxel_size * start, spacing=self.voxel_size,
                             shape=block.shape)
                out[sel] = trilinear_sample(block, local, points[sel])
                # in the band when no corner with a nonzero weight lies outside it
                band[sel] = trilinear_sample(np.abs(block) >= self.background, local, points[sel]) == 0
        far = ~band
        if far.any():
            out[far] = signed_distance(self.surface_vertices, self.surface_faces, points[far],
                                       sign=self.sign).value
        log.debug("vdb sample: %d points, %d in the band", points.shape[0], int(band.sum()))
        return out

    def surface_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Corners ``lo, hi (3,)`` of the bounding box of the surface (the far-field mesh)."""
        return self.surface_vertices.min(axis=0), self.surface_vertices.max(axis=0)

    @property
    def nbytes(self) -> int:
        """Memory of the tree (OpenVDB's ``memUsage``) plus the far-field mesh."""
        return int(self.grid.memUsage() + self.surface_vertices.nbytes + self.surface_faces.nbytes)


def _resign_band(vdb, grid, V: np.ndarray, F: np.ndarray):
    """Copy of the level set whose band voxels take their sign from the generalized winding
    number of ``(V, F)``; inactive tiles get theirs by ``signedFloodFill``."""
    bg = float(grid.background)
    h = float(grid.transform.voxelSize()[0])
    origin = np.array(grid.transform.indexToWorld((0, 0, 0)))
    out = vdb.FloatGrid(background=bg)
    out.transform = grid.transform
    out.gridClass = vdb.GridClass.LEVEL_SET
    out.name = grid.name
    lo, hi = (np.array(c) for c in grid.evalActiveVoxelBoundingBox())
    flipped = total = 0
    for start, shape in _block_starts(lo, hi):
        block = _copy_block(grid, start, shape)
        bandmask = np.abs(block) < bg
        if not bandmask.any():
            continue
        ijk = np.argwhere(bandmask)
        inner = inside(V, F, origin + h * (ijk + start), method="winding")
        values = np.abs(block[bandmask])
        new = np.where(inner, -values, values).astype(np.float32)
        flipped += int(np.count_nonzero(np.signbit(new) != np.signbit(block[bandmask])))
        total += new.size
        fresh = np.full(block.shape, bg, dtype=np.float32)
        fresh[bandmask] = new
        out.copyFromArray(fresh, ijk=tuple(int(s) for s in start), tolerance=0)
    out.signedFloodFill()
    log.debug("winding-number signs: %d of %d band voxels flipped", flipped, total)
    return out
