"""Regular grids over a box and trilinear interpolation on them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import OptionError

__all__ = ["Grid", "trilinear_sample"]


@dataclass(frozen=True)
class Grid:
    """A regular grid of nodes ``origin + spacing * (i, j, k)``.

    Attributes
    ----------
    origin : (3,) float64
        Position of node ``(0, 0, 0)``.
    spacing : float
        Distance between neighbouring nodes (the same along every axis).
    shape : (3,) tuple of int
        Number of nodes along x, y, z.
    """

    origin: np.ndarray
    spacing: float
    shape: tuple[int, int, int]

    @classmethod
    def covering(cls, lo, hi, resolution: int, padding: float = 0.0) -> "Grid":
        """The grid with ``resolution`` nodes along the longest side of the box
        ``[lo - padding, hi + padding]`` and the same spacing along the other sides.

        Parameters
        ----------
        lo, hi : (3,) float
            Corners of the box.
        resolution : int
            Nodes along the longest side, at least 2.
        padding : float
            Absolute margin added on every side.
        """
        if int(resolution) < 2:
            raise OptionError(f"grid resolution must be at least 2, got {resolution}")
        lo = np.asarray(lo, dtype=np.float64) - padding
        hi = np.asarray(hi, dtype=np.float64) + padding
        extent = hi - lo
        spacing = float(extent.max()) / (int(resolution) - 1)
        if not np.isfinite(spacing) or spacing <= 0:
            raise OptionError(f"cannot build a grid over the degenerate box {lo} - {hi}")
        counts = np.ceil(extent / spacing - 1e-9).astype(int) + 1
        # centre the grid on the box along the shorter sides
        origin = (lo + hi) / 2.0 - spacing * (counts - 1) / 2.0
        return cls(origin=origin, spacing=spacing, shape=tuple(int(c) for c in counts))

    @property
    def size(self) -> int:
        """Number of nodes."""
        return int(np.prod(self.shape))

    @property
    def cell_volume(self) -> float:
        """Volume ``spacing^3`` each node stands for (the quadrature weight of Eq. 3)."""
        return self.spacing**3

    @property
    def upper(self) -> np.ndarray:
        """The last node, ``(3,)``: the grid's box is ``[origin, upper]``."""
        return np.asarray(self.origin, dtype=np.float64) + self.spacing * (np.asarray(self.shape) - 1)

    def distance_outside(self, points: np.ndarray) -> np.ndarray:
        """Distance of ``points (k, 3)`` to the grid's box, ``(k,)``, 0 inside it: added to
        the value at the nearest point of the box, it extrapolates a distance field beyond
        the box (an upper bound of the true distance outside a surface the box contains).

        Examples
        --------
        >>> g = Grid(origin=np.zeros(3), spacing=0.5, shape=(3, 3, 3))     # the box [0, 1]^3
        >>> g.upper.tolist(), g.distance_outside(np.array([[0.5, 0.5, 0.5], [2.0, 1.0, 1.0]])).tolist()
        ([1.0, 1.0, 1.0], [0.0, 1.0])
        """
        points = np.asarray(points, dtype=np.float64)
        return np.linalg.norm(points - np.clip(points, self.origin, self.upper), axis=1)

    def axes(self) -> list[np.ndarray]:
        """Node coordinates along x, y and z."""
        return [self.origin[d] + self.spacing * np.arange(self.shape[d]) for d in range(3)]

    def points(self) -> np.ndarray:
        """All nodes, ``(nx * ny * nz, 3)`` float64, x slowest (C order of ``shape``)."""
        X, Y, Z = np.meshgrid(*self.axes(), indexing="ij")
        return np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)


def trilinear_sample(values: np.ndarray, grid: Grid, points: np.ndarray) -> np.ndarray:
    """Trilinear interpolation of node values at arbitrary points.

    Points outside the grid are clamped to its boundary (constant extrapolation along the
    normal of the nearest face).

    Parameters
    ----------
    values : (nx, ny, nz) or (nx, ny, nz, c) float
        Values at the nodes of ``grid``, optionally with ``c`` channels each.
    grid : Grid
    points : (k, 3) float

    Returns
    -------
    (k,) or (k, c) float64

    Examples
    --------
    >>> g = Grid(origin=np.zeros(3), spacing=1.0, shape=(2, 2, 2))
    >>> vals = g.points() @ np.array([1.0, 2.0, 3.0])          # a linear field
    >>> trilinear_sample(vals.reshape(g.shape), g, np.array([[0.5, 0.25, 0.75]]))
    array([3.25])
    >>> both = np.stack([vals, 2 * vals], axis=1).reshape(*g.shape, 2)  # two channels at once
    >>> trilinear_sample(both, g, np.array([[0.5, 0.25, 0.75]]))
    array([[3.25, 6.5 ]])
    """
    values = np.asarray(values, dtype=np.float64)
    if values.shape[:3] != tuple(grid.shape) or values.ndim not in (3, 4):
        raise OptionError(f"values must have the grid's shape {grid.shape} (and optionally a "
                          f"channel axis), got {values.shape}")
    P = (np.asarray(points, dtype=np.float64) - grid.origin) / grid.spacing
    upper = np.asarray(grid.shape) - 1
    P = np.clip(P, 0.0, upper)
    i0 = np.minimum(P.astype(np.int64), np.maximum(upper - 1, 0))  # P >= 0: truncation floors
    t = P - i0
    # the cell's corners by flat index (one gather each, a third of a 3-array fancy index's
    # cost); a side of one node has no second corner along it
    _, ny, nz = grid.shape
    base = (i0[:, 0] * ny + i0[:, 1]) * nz + i0[:, 2]
    sx, sy, sz = (step if up > 0 else 0 for step, up in zip((ny * nz, nz, 1), upper))
    flat = values.reshape(grid.size, -1) if values.ndim == 4 else values.reshape(-1)
    tx, ty, tz = t.T
    if values.ndim == 4:
        tx, ty, tz = tx[:, None], ty[:, None], tz[:, None]

    def lerp(a, b, s):
        return a + (b - a) * s

    c00 = lerp(flat[base], flat[base + sx], tx)
    c10 = lerp(flat[base + sy], flat[base + sx + sy], tx)
    c01 = lerp(flat[base + sz], flat[base + sx + sz], tx)
    c11 = lerp(flat[base + sy + sz], flat[base + sx + sy + sz], tx)
    return lerp(lerp(c00, c10, ty), lerp(c01, c11, ty), tz)
