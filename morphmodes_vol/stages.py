"""Stage products that depend on one mesh only, so they can be built once and shared.

:class:`Registration <morphmodes_vol.register.Registration>` normalizes source and target
*jointly*; its eigenbasis and target SDF therefore depend on both meshes. A dataset pipeline
registers one source onto many targets (or many sources onto one target), so it builds each
product in the frame of its own mesh instead (:func:`source_eigenbasis`, :func:`target_field`)
and maps it into a pair's joint frame when the pair runs:

- the skinning eigenmodes (Eq. 4) of the source in its own unit-diagonal frame, rescaled:
  scaling a mesh by ``a`` leaves the cotangent Laplacian unchanged and scales the lumped mass
  by ``a^2``, so ``W -> W / a`` and ``lambda -> lambda / a^2`` keep ``L W = M W Lambda`` and
  ``W^T M W = I``;
- the target SDF on a grid around the target alone (``padding`` and ``target_grid`` measured
  on the target's own box), scaled by ``a`` into the joint frame; quadrature points outside
  that grid get the exact signed distance (closest point, winding-number sign).

These products differ from ``Registration``'s pair-frame ones only by round-off and
eigenspace bases (the eigenbasis) and by the placement of the target grid nodes (the SDF).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .eigenbasis import mesh_skinning_weights
from .repair import sdf_faces
from .mesh import Normalization, joint_normalization
from .sdf import DenseTargetSDF, Grid
from .sdf.source import SignMethod, signed_distance

__all__ = ["SourceEigenbasis", "TargetField", "source_eigenbasis", "target_field"]

log = logging.getLogger(__name__)


def _frame_ratio(frame: Normalization, own: Normalization) -> float:
    """Scale factor ``a`` from the ``own`` frame to ``frame`` (both map the same world)."""
    return float(frame.scale) / float(own.scale)


@dataclass(frozen=True)
class SourceEigenbasis:
    """Skinning eigenmodes (Eq. 4) of a source, computed in the source's own frame.

    Attributes
    ----------
    weights : (n, m) float64
        ``W^T M W = I`` for the mass matrix of the source in ``frame``.
    eigenvalues : (m,) float64
    frame : Normalization
        The source's own unit-diagonal frame.
    """

    weights: np.ndarray
    eigenvalues: np.ndarray
    frame: Normalization

    def in_frame(self, frame: Normalization) -> tuple[np.ndarray, np.ndarray]:
        """Weights ``(n, m)`` and eigenvalues ``(m,)`` of the same modes in ``frame``."""
        a = _frame_ratio(frame, self.frame)
        return self.weights / a, self.eigenvalues / (a * a)

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"weights": self.weights, "eigenvalues": self.eigenvalues,
                "center": self.frame.center, "scale": np.float64(self.frame.scale)}

    @classmethod
    def from_arrays(cls, a) -> "SourceEigenbasis":
        return cls(np.asarray(a["weights"]), np.asarray(a["eigenvalues"]),
                   Normalization(np.asarray(a["center"]), float(a["scale"])))


def source_eigenbasis(V: np.ndarray, F: np.ndarray, modes: int, seed: int = 0) -> SourceEigenbasis:
    """The eigenbasis stage of a source, independent of any target.

    Parameters
    ----------
    V : (n, 3) float
    F : (f, 3) int
    modes, seed : int
        As in :class:`~morphmodes_vol.RegistrationOptions`.

    Examples
    --------
    >>> from morphmodes_vol.primitives import capsule
    >>> V, F = capsule(count=(8, 8))
    >>> basis = source_eigenbasis(V * 10, F, 3)
    >>> W, lam = basis.in_frame(joint_normalization(V * 10, V * 20))
    >>> W.shape
    (66, 3)
    """
    frame = joint_normalization(V)
    Vn = frame.apply(V)
    W, lam = mesh_skinning_weights(Vn, sdf_faces(Vn, F, "source"), modes, seed=seed)
    return SourceEigenbasis(W, lam, frame)


@dataclass(frozen=True)
class TargetField:
    """The target SDF on a grid around the target alone, in the target's own frame.

    Attributes
    ----------
    sdf : DenseTargetSDF
        Negative inside, own-frame units.
    vertices : (n, 3) float64
        The target in its own frame (for exact values outside the grid).
    faces : (f, 3) int64
    frame : Normalization
        The target's own unit-diagonal frame.
    """

    sdf: DenseTargetSDF
    vertices: np.ndarray
    faces: np.ndarray
    frame: Normalization

    @property
    def nbytes(self) -> int:
        """Memory of the grid values."""
        return int(self.sdf.nbytes)

    def sample(self, points: np.ndarray, frame: Normalization) -> np.ndarray:
        """Signed distance of the target at ``points (k, 3)`` given in ``frame``, in that
        frame's units; ``(k,)``."""
        own = self.frame.apply(frame.undo(points))
        g = self.sdf.grid
        inside = np.all((own >= g.origin) & (own <= g.upper), axis=1)
        values = np.empty(own.shape[0])
        values[inside] = self.sdf.sample(own[inside])
        if not inside.all():
            values[~inside] = signed_distance(self.vertices, self.faces, own[~inside], sign="winding").value
        return values * _frame_ratio(frame, self.frame)

    def to_arrays(self) -> dict[str, np.ndarray]:
        g = self.sdf.grid
        return {"values": self.sdf.values, "origin": g.origin, "spacing": np.float64(g.spacing),
                "vertices": self.vertices, "faces": self.faces,
                "center": self.frame.center, "scale": np.float64(self.frame.scale)}

    @classmethod
    def from_arrays(cls, a) -> "TargetField":
        values = np.asarray(a["values"])
        grid = Grid(np.asarray(a["origin"]), float(a["spacing"]), tuple(int(s) for s in values.shape))
        return cls(DenseTargetSDF(grid, values), np.asarray(a["vertices"]), np.asarray(a["faces"]),
                   Normalization(np.asarray(a["center"]), float(a["scale"])))


def target_field(V: np.ndarray, F: np.ndarray, resolution: int, padding: float,
                 sign: SignMethod = "winding") -> TargetField:
    """The target-SDF stage of a target, independent of any source.

    Parameters
    ----------
    V : (n, 3) float
    F : (f, 3) int
    resolution : int
        Grid nodes along the longest side of the padded box of the target.
    padding : float
        Margin on every side, as a fraction of the target's bounding-box diagonal.
    sign : {"winding", "raycast"}
        Inside test of the target (``RegistrationOptions.target_sign``).

    Examples
    --------
    >>> from morphmodes_vol.primitives import icosphere
    >>> V, F = icosphere(3)
    >>> field = target_field(V, F, 24, 0.1)
    >>> frame = joint_normalization(V, 3 * V)       # a pair's frame: the box of a larger source
    >>> pts = frame.apply(np.array([[0.5, 0, 0], [3.0, 0, 0]]))   # inside / outside the grid
    >>> np.round(field.sample(pts, frame) / frame.scale, 1)     # back to world units
    array([-0.5,  2. ])
    """
    frame = joint_normalization(V)
    Vn = frame.apply(V)
    grid = Grid.covering(Vn.min(axis=0), Vn.max(axis=0), resolution, padding)
    F = sdf_faces(Vn, F, "target")  # as Registration: no degenerate/duplicate, oriented
    sdf = DenseTargetSDF.from_mesh(Vn, F, grid, sign=sign)
    log.debug("target field: %s nodes", grid.shape)
    return TargetField(sdf, Vn, np.asarray(F, dtype=np.int64), frame)
