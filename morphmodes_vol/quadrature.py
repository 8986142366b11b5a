"""Quadrature of Eq. (2) that spends source-SDF queries where they matter.

Eq. (3) sums ``(f - g)^2`` over every node of a regular grid (spacing ``h``, weight ``h^3``).
Far from the target the two distance fields are smooth, and closest-point queries there are
the most expensive ones (a BVH search from far away visits many boxes). The *band*
quadrature keeps the full grid near the target's surface and one point per block of
``s x s x s`` nodes elsewhere:

- the fine grid is cut into blocks of ``s^3`` nodes (fewer at the grid's border);
- a block is *near* when the target's distance field may be below ``band`` somewhere in it.
  A distance field is 1-Lipschitz, so it suffices to test the value at the block's centre:
  ``|g(c)| < band + radius + h`` (``radius`` the half diagonal of the block, ``h`` the slack
  of the trilinear target field);
- a near block contributes its nodes with weight ``h^3`` (Eq. 3 unchanged there); a far
  block contributes its centre with the weight of all its nodes, ``count * h^3`` (the
  midpoint rule on the block).

The quadrature depends on the target alone and is never refreshed: every evaluator builds
the same points (a few milliseconds) for every run, every start and every copy of the
source, so the runs' energies compare directly and
an input moved by a rounding cannot move a node between the fine and the far set
(docs/decisions/0021). Where the registration ends, the source lies on the target, inside
the band; on an open target (a partial scan) its unseen side does not, and the
registration keeps every node there.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .sdf.grid import Grid

__all__ = ["GridBlocks", "band_quadrature", "every_other_node"]

log = logging.getLogger(__name__)


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


def band_quadrature(grid: Grid, g_nodes: np.ndarray, sample_target, band: float, factor: int,
                    points: np.ndarray | None = None):
    """The band quadrature of ``grid`` around the target's surface (module docstring).

    Parameters
    ----------
    grid : Grid
        The fine quadrature grid of Eq. (3), ``N`` nodes.
    g_nodes : (N,) float
        Target SDF at the grid's nodes.
    sample_target : callable
        ``points (B, 3) -> (B,)`` target SDF, used once at the block centres.
    band : float
        Half width of the fine band around the target's surface (normalized units).
    factor : int
        Nodes per block side away from the surface (``s``).
    points : (N, 3) float, optional
        ``grid.points()``, when the caller already holds it.

    Returns
    -------
    Q : (k, 3) float64
        The near blocks' nodes, then the far blocks' centres.
    g : (k,) float64
        The target SDF there.
    w : (k,) float64
        Their weights: ``h^3`` a node, ``count * h^3`` a far centre.

    Examples
    --------
    >>> g = Grid(origin=np.zeros(3), spacing=1.0, shape=(8, 8, 8))
    >>> plane = lambda P: P[:, 0] - 1.0                     # the target: the plane x = 1
    >>> Q, gq, w = band_quadrature(g, plane(g.points()), plane, band=1.0, factor=2)
    >>> float(w.sum()) == g.size * g.cell_volume            # the weights cover the box
    True
    >>> int((w == 1.0).sum()), int((w == 8.0).sum())        # nodes x <= 3; 32 far blocks
    (256, 32)
    """
    points = grid.points() if points is None else points
    blocks = GridBlocks.of(grid, factor, points)
    g_nodes = np.asarray(g_nodes, dtype=np.float64)
    g_centers = np.asarray(sample_target(blocks.centers), dtype=np.float64)
    near = np.abs(g_centers) < band + blocks.radius + grid.spacing
    fine = near[blocks.block_of_node]
    far = np.flatnonzero(~near)
    h3 = grid.cell_volume
    Q = np.concatenate([points[fine], blocks.centers[far]])
    g = np.concatenate([g_nodes[fine], g_centers[far]])
    w = np.concatenate([np.full(int(fine.sum()), h3), blocks.counts[far] * h3])
    log.debug("band quadrature: %d nodes + %d block centres (of %d nodes)", int(fine.sum()), far.size,
              points.shape[0])
    return Q, g, w


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
