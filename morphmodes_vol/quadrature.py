"""Quadrature of Eq. (2) that spends source-SDF queries where they matter.

Eq. (3) sums ``(f - g)^2`` over every node of a regular grid (spacing ``h``, weight ``h^3``).
Far from both surfaces the two distance fields are smooth, and closest-point queries there
are the most expensive ones (a BVH search from far away visits many boxes). The *band*
quadrature keeps the full grid near the surfaces and one node per block of ``s x s x s``
nodes elsewhere:

- the fine grid is cut into blocks of ``s^3`` nodes (fewer at the grid's border);
- a block is *near* when a distance field may be below ``band`` somewhere in it. Distance
  fields are 1-Lipschitz, so it suffices to test the value at the block's centre:
  ``|f(c)| < band + radius + margin`` (``radius`` the half diagonal of the block, ``margin``
  how far the source may move before the classification is refreshed); likewise for ``g``;
- a near block contributes its nodes with weight ``h^3`` (Eq. 3 unchanged there); a far
  block contributes its centre with the weight of all its nodes, ``count * h^3`` (the
  midpoint rule on the block).

The classification depends on where the source is, so it is refreshed whenever some vertex
has moved by more than ``margin`` since the last refresh (:meth:`BandEnergy.refresh`), which
keeps every node within ``band`` of the current source in the fine set. Energies of
different refreshes are different quadratures of the same integral; the optimizer compares
energies only within one.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from .energy import EnergyEvaluation, KnownQueries, SDFEnergy
from .sdf.grid import Grid
from .sdf.source import SignMethod, closest_points

__all__ = ["GridBlocks", "BandEnergy", "every_other_node"]

log = logging.getLogger(__name__)

# normalized units; above the float32 error of Open3D's closest-face search (about 1e-7)
_BOUND_SLACK = 1e-6


@dataclass(frozen=True)
class GridBlocks:
    """The nodes of a grid grouped into blocks of ``factor^3`` nodes.

    Attributes
    ----------
    block_of_node : (N,) int64
        Block index of every node (nodes in the order of :meth:`Grid.points`).
    centers : (B, 3) float64
        Mean position of each block's nodes.
    counts : (B,) int64
        Nodes per block.
    radius : float
        Largest distance from a block's centre to one of its nodes.
    """

    block_of_node: np.ndarray
    centers: np.ndarray
    counts: np.ndarray
    radius: float

    @classmethod
    def of(cls, grid: Grid, factor: int, points: np.ndarray | None = None) -> "GridBlocks":
        """Blocks of ``factor`` nodes per axis over ``grid``; ``points`` is ``grid.points()``
        when the caller already has it.

        Examples
        --------
        >>> g = Grid(origin=np.zeros(3), spacing=1.0, shape=(5, 4, 4))
        >>> b = GridBlocks.of(g, 2)
        >>> b.counts.tolist()            # 3 x 2 x 2 blocks, the last x-slab one node thick
        [8, 8, 8, 8, 8, 8, 8, 8, 4, 4, 4, 4]
        >>> b.centers[0].tolist()
        [0.5, 0.5, 0.5]
        """
        shape = np.asarray(grid.shape)
        nb = -(-shape // factor)  # ceil
        idx = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1).reshape(-1, 3)
        bidx = idx // factor
        block = np.ravel_multi_index(bidx.T, tuple(nb))
        counts = np.bincount(block, minlength=int(np.prod(nb)))
        points = grid.points() if points is None else points
        centers = np.stack(
            [np.bincount(block, weights=points[:, d], minlength=counts.size) for d in range(3)], 1
        ) / np.maximum(counts, 1)[:, None]
        radius = float(np.sqrt(3.0) * (factor - 1) * grid.spacing / 2.0)
        return cls(block_of_node=block, centers=centers, counts=counts, radius=radius)


class BandEnergy:
    """Eq. (3) on the band quadrature, with the interface of :class:`SDFEnergy`.

    Parameters
    ----------
    F : (f, 3) int
        Source triangles.
    grid : Grid
        The fine quadrature grid of Eq. (3).
    g_nodes : (N,) float
        Target SDF at the grid's nodes.
    sample_target : callable
        ``points (B, 3) -> (B,)`` target SDF, used once at the block centres.
    band : float
        Half width of the fine band around each surface (normalized units).
    factor : int
        Nodes per block side away from the surfaces (``s``).
    margin : float
        Vertex motion allowed before the band is recomputed.
    sign, samples
        As in :class:`SDFEnergy`.
    points : (N, 3) float, optional
        ``grid.points()``, when the caller already holds it (not copied).
    confidence : ((N,) float, callable) or None
        The confidence of an open target's field (:mod:`morphmodes_vol.sdf.confidence`) at
        the nodes, and its sampler for the block centres: it multiplies the weights.

    Counters: ``evaluations``; ``partial_evaluations``, those after a refresh that queried
    only the points new to the band (:meth:`evaluate`); ``points_queried``, the points sent
    to the mesh queries; ``refreshes``; ``centres_queried``, the block centres a refresh
    sent to the distance query (:meth:`refresh`).
    """

    def __init__(self, F, grid: Grid, g_nodes, sample_target, band: float, factor: int,
                 margin: float, sign: SignMethod = "raycast", samples: int = 1,
                 points: np.ndarray | None = None, confidence=None):
        self.F = np.ascontiguousarray(F, dtype=np.int64)
        self.grid = grid
        self.points = grid.points() if points is None else points
        self.blocks = GridBlocks.of(grid, factor, self.points)
        self.g_nodes = np.asarray(g_nodes, dtype=np.float64)
        self.g_centers = np.asarray(sample_target(self.blocks.centers), dtype=np.float64)
        n_nodes = self.points.shape[0]
        self.c_nodes, self.c_centers = ((np.ones(n_nodes), np.ones(self.blocks.counts.size)) if confidence is None
                                        else (np.asarray(confidence[0], dtype=np.float64),
                                              np.asarray(confidence[1](self.blocks.centers), dtype=np.float64)))
        self.band, self.margin = float(band), float(margin)
        self.sign, self.samples = sign, samples
        reach = self.band + self.blocks.radius
        self.near_target = np.abs(self.g_centers) < reach + grid.spacing  # trilinear slack
        self._anchor: np.ndarray | None = None
        # lower bounds of the source's distance at the block centres, valid at _anchor
        self._lower = np.full(self.blocks.counts.size, -np.inf)
        self._inner: SDFEnergy | None = None
        self._ids: np.ndarray | None = None  # each point's node, or N + its block (far centres)
        self._last = None  # (X, ids, evaluation, signed distances) of the last evaluation
        self.evaluations = 0
        self.partial_evaluations = 0
        self.points_queried = 0
        self.centres_queried = 0
        self.seconds = 0.0
        self.refreshes = 0

    @property
    def weights(self) -> np.ndarray:
        return self._inner.weights

    @property
    def Q(self) -> np.ndarray:
        return self._inner.Q

    def refresh(self, X: np.ndarray, force: bool = False) -> bool:
        """Recompute the band for the source vertices ``X (n, 3)`` if some vertex moved by
        more than ``margin`` since the last refresh (or ``force``). Returns whether it did."""
        moved = 0.0
        if self._anchor is not None:
            moved = float(np.sqrt(np.max(np.sum((X - self._anchor) ** 2, axis=1))))
            if not force and moved <= self.margin:
                return False
        t0 = time.perf_counter()
        reach = self.band + self.blocks.radius + self.margin
        # No vertex moved by more than `moved`, so no point of the surface did (each is a
        # convex combination of its triangle's corners): the distance at a centre fell by at
        # most `moved`. Only the centres whose bound is below the reach are queried; the
        # others stay far, as a query would find (the slack covers the float32 search).
        # Centres near the target are near whatever the source does, and never queried.
        self._lower -= moved
        ask = ~self.near_target & (self._lower <= reach + _BOUND_SLACK)
        if ask.any():
            self._lower[ask] = closest_points(X, self.F, self.blocks.centers[ask]).distance
        self.centres_queried += int(ask.sum())
        near = self.near_target | (self._lower < reach)
        fine = near[self.blocks.block_of_node]
        far = np.flatnonzero(~near)
        h3 = self.grid.cell_volume
        Q = np.concatenate([self.points[fine], self.blocks.centers[far]])
        g = np.concatenate([self.g_nodes[fine], self.g_centers[far]])
        w = np.concatenate([h3 * self.c_nodes[fine], self.blocks.counts[far] * h3 * self.c_centers[far]])
        self._inner = SDFEnergy(self.F, Q, g, w, sign=self.sign, samples=self.samples)
        self._ids = np.concatenate([np.flatnonzero(fine), self.points.shape[0] + far])
        self._anchor = np.array(X, copy=True)
        self.refreshes += 1
        self.seconds += time.perf_counter() - t0
        log.debug("band quadrature: %d fine nodes + %d block centres (of %d nodes)",
                  int(fine.sum()), far.size, self.points.shape[0])
        return True

    def evaluate(self, X: np.ndarray) -> EnergyEvaluation:
        """Energy and vertex gradient at ``X (n, 3)`` on the current band quadrature.

        The first evaluation after a refresh is usually at the vertices of the last
        evaluation (the optimizer re-evaluates the same state on the new quadrature): then
        the points both quadratures share keep their answers and only the others are
        queried (``partial_evaluations``), with the same result as a full evaluation.
        """
        if self._inner is None:
            self.refresh(X, force=True)
        known = self._known(X)
        ev = self._inner.evaluate(X, known)
        self.evaluations += 1
        self.partial_evaluations += known is not None
        self.points_queried += self._inner.points_queried
        self._inner.points_queried = 0
        self.seconds += self._inner.seconds
        self._inner.seconds = 0.0
        self._last = (np.array(X, copy=True), self._ids, ev, self._inner.last_value)
        return ev

    def _known(self, X: np.ndarray) -> KnownQueries | None:
        """The answers of the last evaluation at the current quadrature's points, when that
        evaluation was at these vertices ``X`` on another quadrature; else ``None``."""
        if self._last is None:
            return None
        X_last, ids_last, ev, value_last = self._last
        if ids_last is self._ids or X_last.shape != X.shape or not np.array_equal(X_last, X):
            return None
        # both id lists are ascending (fine nodes, then N + far blocks)
        pos = np.minimum(np.searchsorted(ids_last, self._ids), len(ids_last) - 1)
        mask = ids_last[pos] == self._ids
        if not mask.any():
            return None
        old = pos[mask]
        return KnownQueries(mask=mask, value=value_last[old], faces=ev.closest_faces[old],
                            barycentrics=ev.barycentrics[old], normal=ev.normal[old])


def every_other_node(grid: Grid) -> tuple[Grid, np.ndarray]:
    """The grid of every second node of ``grid`` along each axis (spacing ``2h``) and the
    flat indices ``(M,)`` of its nodes among ``grid``'s, so node values subsample exactly.

    Examples
    --------
    >>> g = Grid(origin=np.zeros(3), spacing=0.5, shape=(5, 4, 3))
    >>> c, idx = every_other_node(g)
    >>> c.shape, c.spacing, bool(np.allclose(c.points(), g.points()[idx]))
    ((3, 2, 2), 1.0, True)
    """
    sub = [np.arange(0, n, 2) for n in grid.shape]
    I, J, K = np.meshgrid(*sub, indexing="ij")
    idx = np.ravel_multi_index((I.ravel(), J.ravel(), K.ravel()), grid.shape)
    coarse = Grid(origin=np.asarray(grid.origin, dtype=np.float64), spacing=2.0 * grid.spacing,
                  shape=tuple(len(a) for a in sub))
    return coarse, idx
