"""Optional landmarks: a few source vertices pinned to target points, added to Eq. (3).

The paper notes that its energy is compatible with additional terms such as landmarks. With
``L`` pairs (source vertex ``i_l``, target point ``p_l``) the total energy is

    E_total(x) = E_sdf(x) + E_lm(x),
    E_lm(x) = weight * V / L * sum_l ||x_{i_l} - p_l||^2

in the normalized frame (union bounding-box diagonal 1), ``V`` the volume of the quadrature
box (the sum of Eq. 3's weights). Unit of ``weight``: ``E_sdf / V`` is the mean squared SDF
residual over the box and ``E_lm / V`` is ``weight`` times the mean squared landmark
distance, so ``weight = 1`` makes a landmark's squared miss count as much as the same
squared SDF residual spread over the whole box, whatever the mesh's units, the grid
resolution or the number of landmarks.

Gradient: ``dE_lm/dx_{i_l} = 2 weight V / L (x_{i_l} - p_l)``. In the subspace, ``x_i`` is
row ``i`` of the skinning matrix ``C (n, 4m)`` times each coordinate's ``4m`` coefficients
(Eq. 6), so the term's exact Hessian (it is quadratic) is ``2 weight V / L * C_L^T C_L`` on
each coordinate's block: the Gauss-Newton block that :meth:`LandmarkEnergy.normal_matrix`
hands to the Levenberg-Marquardt step (:mod:`morphmodes_vol.optimize.gauss_newton`).

Landmark files: CSV, one landmark per line, ``source_vertex_index, x, y, z`` (target
point in the target's original frame), an optional header line, ``#`` comments and blank
lines allowed.
"""

from __future__ import annotations

import csv
import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .energy import AddedTerm, EnergyEvaluation
from .errors import LandmarkError
from .optimize.gauss_newton import _assemble

__all__ = ["Landmarks", "load_landmarks", "as_landmarks", "LandmarkEnergy", "LandmarkEvaluation",
           "landmark_rms"]


@dataclass(frozen=True)
class Landmarks:
    """Source vertex indices and the target points they should reach.

    Attributes
    ----------
    indices : (L,) int64
        Source vertex of each landmark, distinct.
    points : (L, 3) float64
        Target point of each landmark (the target's original frame).
    label : str
        Where they came from (a file name, for messages and reports).
    """

    indices: np.ndarray
    points: np.ndarray
    label: str = "landmarks"

    def __len__(self) -> int:
        return int(self.indices.shape[0])


def _fail(label: str, line: int | None, what: str):
    where = label if line is None else f"{label}, line {line}"
    raise LandmarkError(f"{where}: {what}")


def load_landmarks(path: str | os.PathLike, n_vertices: int | None = None) -> Landmarks:
    """Read a landmark CSV: ``source_vertex_index, x, y, z`` per line.

    A first line without any number is a header; blank lines and lines starting with ``#``
    are skipped.

    Parameters
    ----------
    path : path
    n_vertices : int, optional
        Source vertex count, to check the indices.

    Returns
    -------
    Landmarks

    Raises
    ------
    LandmarkError
        Unreadable or empty file, wrong column count, non-integer or out-of-range index,
        duplicate index, non-finite coordinate; the message names the file and the line.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "lm.csv"
    >>> _ = p.write_text("source_vertex_index,x,y,z\\n3, 0.5, 0, 1\\n7, 1, 2, 3\\n")
    >>> lm = load_landmarks(p, n_vertices=10)
    >>> lm.indices.tolist(), lm.points[0].tolist()
    ([3, 7], [0.5, 0.0, 1.0])
    """
    label = str(path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:  # a BOM is no header
            rows = list(enumerate(csv.reader(fh), start=1))
    except OSError as exc:
        _fail(label, None, f"cannot read the landmark file ({exc.strerror})")
    except UnicodeDecodeError:
        _fail(label, None, "not a text (CSV) file")
    indices, points, lines = [], [], []
    header_allowed = True
    for line, row in rows:
        fields = [f.strip() for f in row]
        if not any(fields) or fields[0].startswith("#"):
            continue
        if header_allowed and not any(_is_number(f) for f in fields):
            header_allowed = False  # a header: no number in it, once, before any landmark
            continue
        header_allowed = False
        if len(fields) != 4:
            _fail(label, line, f"expected 4 columns (source_vertex_index, x, y, z), got {len(fields)}")
        try:
            index = float(fields[0])
        except ValueError:
            _fail(label, line, f"source vertex index {fields[0]!r} is not a number")
        if not index.is_integer():
            _fail(label, line, f"source vertex index {fields[0]!r} is not an integer")
        try:
            xyz = [float(f) for f in fields[1:]]
        except ValueError:
            _fail(label, line, f"coordinates {fields[1:]} are not all numbers")
        indices.append(int(index))
        points.append(xyz)
        lines.append(line)
    if not indices:
        _fail(label, None, "no landmark (expected lines 'source_vertex_index, x, y, z')")
    return _validated(np.array(indices, dtype=np.int64), np.array(points, dtype=np.float64),
                      n_vertices, label, lines)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _validated(indices: np.ndarray, points: np.ndarray, n_vertices: int | None, label: str,
               lines: list[int] | None = None) -> Landmarks:
    """The one landmark validator; ``lines[k]`` is the file line of landmark ``k``."""

    def line(k: int) -> int | None:
        return None if lines is None else lines[k]

    def name(k: int) -> str:
        return "" if lines is not None else f"landmark {k}: "

    if indices.ndim != 1 or points.shape != (indices.shape[0], 3):
        _fail(label, None, f"expected indices (L,) and points (L, 3), got {indices.shape} and {points.shape}")
    if indices.shape[0] == 0:
        _fail(label, None, "no landmark")
    bad = np.flatnonzero(~np.isfinite(points).all(axis=1))
    if bad.size:
        _fail(label, line(bad[0]), f"{name(bad[0])}target point {points[bad[0]].tolist()} is not finite")
    bad = np.flatnonzero(indices < 0)
    if n_vertices is not None:
        bad = np.flatnonzero((indices < 0) | (indices >= n_vertices))
    if bad.size:
        k = bad[0]
        _fail(label, line(k), f"{name(k)}source vertex index {indices[k]} is out of range "
                              f"[0, {n_vertices if n_vertices is not None else 'n'})")
    order = np.argsort(indices, kind="stable")
    dup = np.flatnonzero(np.diff(indices[order]) == 0)
    if dup.size:
        k = order[dup[0] + 1]
        _fail(label, line(k), f"{name(k)}source vertex {indices[k]} has a landmark already "
                              f"({'line ' + str(line(order[dup[0]])) if lines else 'landmark ' + str(order[dup[0]])})")
    return Landmarks(indices=indices, points=points, label=label)


def as_landmarks(value, n_vertices: int, label: str = "landmarks") -> Landmarks:
    """Landmarks from a CSV path, a :class:`Landmarks`, or a pair ``(indices (L,) int,
    points (L, 3) float)``, validated against the source's ``n_vertices``.

    Examples
    --------
    >>> lm = as_landmarks(([0, 5], [[0, 0, 0], [1, 1, 1]]), n_vertices=6)
    >>> lm.indices.dtype, lm.points.shape
    (dtype('int64'), (2, 3))
    """
    if isinstance(value, (str, os.PathLike)):
        return load_landmarks(Path(value), n_vertices)
    if isinstance(value, Landmarks):
        return _validated(value.indices, value.points, n_vertices, value.label)
    try:
        raw_indices, raw_points = value
    except (TypeError, ValueError):
        _fail(label, None, "expected a CSV path or a pair (indices (L,) int, points (L, 3) float)")
    raw_indices = np.asarray(raw_indices)
    if raw_indices.size and not np.issubdtype(raw_indices.dtype, np.integer):
        _fail(label, None, f"indices must be integers, got dtype {raw_indices.dtype}")
    try:
        points = np.array(raw_points, dtype=np.float64)
    except (TypeError, ValueError):
        _fail(label, None, "points must be an (L, 3) array of numbers")
    return _validated(raw_indices.astype(np.int64), points, n_vertices, label)


def landmark_rms(vertices: np.ndarray, landmarks: Landmarks) -> float:
    """Root mean square distance between ``vertices[indices] (L, 3)`` and the points, in
    the frame the two are given in."""
    d = vertices[landmarks.indices] - landmarks.points
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


@dataclass(frozen=True)
class LandmarkEvaluation(EnergyEvaluation):
    """An :class:`~morphmodes_vol.energy.EnergyEvaluation` of ``E_sdf + E_lm``:
    ``energy`` and ``gradient`` are the totals, ``residual`` and the correspondences are the
    SDF term's, ``landmark_energy`` is ``E_lm`` (counted in ``extra_energy``, so
    ``rms_residual`` stays the SDF's)."""

    landmark_energy: float = 0.0


class LandmarkEnergy(AddedTerm):
    """``E_sdf + E_lm`` with the interface of :class:`~morphmodes_vol.energy.SDFEnergy`
    (:class:`~morphmodes_vol.energy.AddedTerm`), so the optimizers of
    :mod:`morphmodes_vol.optimize` see no difference.

    Parameters
    ----------
    inner : SDFEnergy
        Eq. (3).
    indices : (L,) int
        Landmark source vertices.
    points : (L, 3) float
        Their target points, in the normalized frame.
    weight : float
        Dimensionless weight (module docstring).
    volume : float
        Volume of the quadrature box, ``V`` (normalized units).

    Examples
    --------
    >>> import numpy as np
    >>> from morphmodes_vol.energy import SDFEnergy
    >>> from morphmodes_vol.primitives import icosphere
    >>> V, F = icosphere(1)
    >>> sdf = SDFEnergy(F, np.zeros((1, 3)), np.array([-1.0]), 1.0)
    >>> E = LandmarkEnergy(sdf, [0], V[[0]] + [0.1, 0, 0], weight=2.0, volume=1.0)
    >>> round(E.evaluate(V).landmark_energy, 6)      # 2 * 1 / 1 * 0.1^2
    0.02
    """

    def __init__(self, inner, indices, points, weight: float, volume: float):
        super().__init__(inner)
        self.indices = np.asarray(indices, dtype=np.int64)
        self.points = np.asarray(points, dtype=np.float64)
        self.coefficient = float(weight) * float(volume) / max(self.indices.shape[0], 1)
        self._normal: dict[int, np.ndarray] = {}

    def term(self, X: np.ndarray) -> tuple[float, np.ndarray]:
        """``E_lm`` and its vertex gradient ``(n, 3)`` at ``X (n, 3)``."""
        d = X[self.indices] - self.points
        grad = np.zeros_like(X, dtype=np.float64)
        np.add.at(grad, self.indices, 2.0 * self.coefficient * d)
        return self.coefficient * float(np.sum(d * d)), grad

    def _evaluation(self, total: EnergyEvaluation, value: float) -> LandmarkEvaluation:
        fields = {f.name: getattr(total, f.name) for f in dataclasses.fields(EnergyEvaluation)}
        return LandmarkEvaluation(**fields, landmark_energy=value)

    def term_normal_matrix(self, basis, m: int, X: np.ndarray | None = None) -> np.ndarray:
        """The term's block of the Gauss-Newton matrix in the first ``m`` modes, in the T
        layout of :class:`~morphmodes_vol.optimize.gauss_newton.NormalEquations`:
        ``coefficient * C_L^T C_L`` on each coordinate block, ``(12m, 12m)`` (``C_L`` the
        landmark rows of the skinning matrix; half the term's Hessian, as ``A`` is half
        the Gauss-Newton Hessian of Eq. 3); constant, ``X`` is not used."""
        if m not in self._normal:
            CL = basis.skinning_matrix(m)[self.indices]
            block = self.coefficient * (CL.T @ CL)
            self._normal[m] = _assemble({(a, a): block for a in range(3)}, m)
        return self._normal[m]
