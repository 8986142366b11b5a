"""Mesh input: loading without processing, the one validator, and joint normalization.

Every public entry point of the library goes through :func:`as_mesh`, which accepts a path,
a :class:`trimesh.Trimesh` or a ``(V, F)`` tuple and returns validated copies.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Union

import numpy as np

from .errors import MeshLoadError, MeshValidationError

__all__ = [
    "MeshLike",
    "MESH_EXTENSIONS",
    "as_mesh",
    "load_mesh",
    "validate_mesh",
    "Normalization",
    "joint_normalization",
    "bbox_diagonal",
]

log = logging.getLogger(__name__)

# What load_mesh reads (trimesh's mesh readers); other extensions are refused up front.
MESH_EXTENSIONS = ("obj", "ply", "off", "stl", "glb", "gltf")

NO_FACES = (
    "no faces (a point cloud?); source and target must be triangle surfaces, since the "
    "signed distance needs an inside: reconstruct a surface first (e.g. Poisson)"
)

MeshLike = Union[str, os.PathLike, "trimesh.Trimesh", tuple]  # noqa: F821


def validate_mesh(V, F, name: str = "mesh", min_vertices: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Check a triangle mesh and return float64/int64 copies.

    Parameters
    ----------
    V : (n, 3) array_like of float
        Vertex positions.
    F : (m, 3) or (m, 4) array_like of int
        Triangle (or quad) vertex indices, 0-based.
    name : str
        What the mesh is (a file name, ``"source"``), used in error messages.
    min_vertices : int
        Fewest vertices accepted (registration needs 4: an affine map in 3D).

    Returns
    -------
    V : (n, 3) float64
        A copy of the vertices (the input is never modified).
    F : (m, 3) int64
        A copy of the faces (``(2 m, 3)`` for quads).

    Quads ``(m, 4)`` are split into triangles ``(a, b, c), (a, c, d)``: all first halves,
    then all second halves, so ``F`` has ``2 m`` rows (trimesh splits the quads of a file
    into the same triangles while reading).

    Raises
    ------
    MeshValidationError
        If a shape is wrong, a coordinate is not finite, an index is out of range or the
        mesh has no faces.

    Examples
    --------
    >>> V, F = validate_mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], "triangle")
    >>> V.dtype, F.dtype
    (dtype('float64'), dtype('int64'))
    """
    try:
        V = np.array(V, dtype=np.float64, copy=True)
    except (TypeError, ValueError) as exc:
        raise MeshValidationError(f"{name}: vertices are not a numeric array ({exc})") from None
    if V.ndim != 2 or V.shape[1] != 3:
        raise MeshValidationError(
            f"{name}: vertices must have shape (n, 3), got shape {V.shape}"
        )
    if V.shape[0] < min_vertices:
        raise MeshValidationError(
            f"{name}: needs at least {min_vertices} vertices, got {V.shape[0]}"
        )
    bad = ~np.isfinite(V).all(axis=1)
    if bad.any():
        raise MeshValidationError(
            f"{name}: {int(bad.sum())} vertices have NaN or infinite coordinates "
            f"(first: vertex {int(np.flatnonzero(bad)[0])})"
        )
    try:
        F_in = np.asarray(F)
    except ValueError as exc:  # ragged lists of polygons
        raise MeshValidationError(f"{name}: faces are not a rectangular array ({exc})") from None
    if F_in.size == 0:
        raise MeshValidationError(f"{name}: {NO_FACES}")
    if F_in.ndim != 2 or F_in.shape[1] not in (3, 4):
        raise MeshValidationError(
            f"{name}: faces must be triangles (m, 3) or quads (m, 4), got shape {F_in.shape}"
        )
    if not np.issubdtype(F_in.dtype, np.integer):
        with np.errstate(invalid="ignore"):  # NaN and inf are not integers either
            integral = np.issubdtype(F_in.dtype, np.floating) and np.all(np.mod(F_in, 1) == 0)
        if not integral:
            raise MeshValidationError(f"{name}: face indices must be integers")
    if not np.all(np.abs(F_in) < 2**62):  # also catches NaN, inf and int64 overflow
        raise MeshValidationError(f"{name}: face indices must be finite integers")
    F = F_in.astype(np.int64, copy=True)
    if F.min() < 0 or F.max() >= V.shape[0]:
        raise MeshValidationError(
            f"{name}: face indices must lie in [0, {V.shape[0] - 1}], "
            f"found range [{int(F.min())}, {int(F.max())}]"
        )
    if F.shape[1] == 4:
        # quads (a b c d) -> triangles (a b c), (a c d), as trimesh does when reading files
        log.warning("%s: %d quads split into triangles", name, F.shape[0])
        F = np.concatenate([F[:, [0, 1, 2]], F[:, [0, 2, 3]]])
    return V, F


def load_mesh(path: str | os.PathLike, min_vertices: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh file without merging or reordering vertices.

    Parameters
    ----------
    path : str or PathLike
        Any format trimesh reads (OBJ, PLY, OFF, STL, ...).

    Returns
    -------
    V : (n, 3) float64
    F : (m, 3) int64

    Raises
    ------
    MeshLoadError
        If the file is missing, empty, unreadable or not a triangle mesh.
    MeshValidationError
        If the mesh read fails :func:`validate_mesh`.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise MeshLoadError(f"{path}: no such file")
    ext = path.suffix.lower().lstrip(".")
    if ext not in MESH_EXTENSIONS:
        raise MeshLoadError(
            f"{path}: unsupported file extension {path.suffix or '(none)'!r}; "
            f"mesh files must be one of {', '.join(MESH_EXTENSIONS)}"
        )
    if path.stat().st_size == 0:
        raise MeshLoadError(f"{path}: the file is empty")
    try:
        # process=False: no merging/reordering; maintain_order=True: the OBJ loader otherwise
        # drops unreferenced vertices, which shifts every later index (vertex order is the
        # ground truth of an evaluation).
        mesh = trimesh.load(str(path), process=False, maintain_order=True)
        if isinstance(mesh, trimesh.Scene) and mesh.geometry:  # glTF: one mesh of all parts
            mesh = trimesh.load(str(path), process=False, force="mesh", maintain_order=True)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise MeshLoadError(f"{path}: cannot be read as a mesh ({type(exc).__name__}: {exc})") from None
    if isinstance(mesh, trimesh.PointCloud) and len(mesh.vertices):
        raise MeshLoadError(f"{path}: {len(mesh.vertices)} vertices but {NO_FACES}")
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.vertices) == 0:
        raise MeshLoadError(f"{path}: no vertices found: not a valid {ext.upper()} mesh file")
    if len(mesh.faces) == 0:
        raise MeshLoadError(f"{path}: {len(mesh.vertices)} vertices but {NO_FACES}")
    return validate_mesh(mesh.vertices, mesh.faces, name=str(path), min_vertices=min_vertices)


def as_mesh(mesh: MeshLike, name: str = "mesh", min_vertices: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Validated ``(V, F)`` copies of a path, a ``trimesh.Trimesh`` or a ``(V, F)`` tuple.

    Returns
    -------
    V : (n, 3) float64
    F : (m, 3) int64
    """
    if isinstance(mesh, (str, os.PathLike)):
        return load_mesh(mesh, min_vertices=min_vertices)
    if isinstance(mesh, tuple) and len(mesh) == 2:
        return validate_mesh(mesh[0], mesh[1], name=name, min_vertices=min_vertices)
    if hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        return validate_mesh(mesh.vertices, mesh.faces, name=name, min_vertices=min_vertices)
    if hasattr(mesh, "vertices") or (isinstance(mesh, np.ndarray) and mesh.ndim == 2):
        raise MeshValidationError(f"{name}: a set of points: {NO_FACES}")
    raise MeshValidationError(
        f"{name}: expected a file path, a trimesh.Trimesh or a (V, F) tuple, "
        f"got {type(mesh).__name__}"
    )


def bbox_diagonal(V: np.ndarray) -> float:
    """Length of the diagonal of the axis-aligned bounding box of ``V (n, 3)``."""
    V = np.asarray(V, dtype=np.float64)
    return float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))


@dataclass(frozen=True)
class Normalization:
    """A similarity ``x -> (x - center) * scale`` (no rotation).

    Attributes
    ----------
    center : (3,) float64
    scale : float
    """

    center: np.ndarray
    scale: float

    def apply(self, V: np.ndarray) -> np.ndarray:
        """Original frame to normalized frame: ``(n, 3) -> (n, 3)``."""
        return (np.asarray(V, dtype=np.float64) - self.center) * self.scale

    def undo(self, V: np.ndarray) -> np.ndarray:
        """Normalized frame to original frame: ``(n, 3) -> (n, 3)``."""
        return np.asarray(V, dtype=np.float64) / self.scale + self.center


def joint_normalization(*vertex_sets: np.ndarray) -> Normalization:
    """The similarity that maps the union bounding box of all sets to unit diagonal, centered.

    The same transform is applied to source and target, so their relative pose and scale
    are untouched; it is undone on export.

    Parameters
    ----------
    *vertex_sets : (n_i, 3) float
    """
    allV = np.concatenate([np.asarray(V, dtype=np.float64).reshape(-1, 3) for V in vertex_sets])
    lo, hi = allV.min(axis=0), allV.max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    if not np.isfinite(diag) or diag <= 0:
        raise MeshValidationError(
            f"the meshes have a degenerate joint bounding box (diagonal {diag})"
        )
    return Normalization(center=(lo + hi) / 2.0, scale=1.0 / diag)
