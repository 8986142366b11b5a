"""A Levenberg-Marquardt step in the active skinning subspace (our fast optimizer).

The energy of Eq. (3) is a weighted sum of squares, ``E = sum_i w_i r_i^2`` with
``r_i = f(Q_i; x) - g(Q_i)``. With the closest-point correspondences and signs of the
current configuration frozen, the residual is linear in the vertices to first order:
``dr_i / dv_{t_i c} = -b_ic n_i`` (see :mod:`morphmodes_vol.energy`), and through
``x = B z + x0`` (Eq. 5) linear in the subspace coefficients, ``J_z = J_x B``. The model

    E(z + d) ~ E + 2 d^T J_z^T W r + d^T J_z^T W J_z d

has only ``12 m`` unknowns, so its normal equations are solved exactly. We damp them with
``lambda * B^T B`` (a trust region on the vertex motion, Levenberg's choice in the metric of
the vertices, so the damping does not depend on how the modes are scaled) and accept a step
only when the *true* energy (one full source-SDF evaluation) decreases; ``lambda`` adapts
by Nielsen's rule. An accepted step's evaluation is also the next linearization, so a step
costs one source-SDF evaluation when the model is good.

``J_z^T W J_z`` is assembled without forming ``J_z`` (``k x 12m``, ``k`` the quadrature
points): with ``P`` the ``k x n`` closest-point interpolation matrix (barycentric weights) and
``C = [w_j(x0_i) [x0_i 1]]`` the ``n x 4m`` skinning matrix, its ``(a, a')`` coordinate block
is ``C^T P^T diag(w n_a n_a') P C``. ``P^T diag(.) P`` is gathered per closest triangle
(``k`` is often 100x the triangle count) and scattered to an ``n x n`` sparse matrix with the
mesh's adjacency pattern (:class:`SparsePattern`, sorted once); then six small dense
products.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..eigenbasis.lbs import LBSBasis
from ..energy import EnergyEvaluation

__all__ = ["subspace_normal_equations", "subspace_metric", "lm_solve", "damping_factor", "NormalEquations",
           "VertexBlocks", "SparsePattern", "face_corner_pattern"]


class SparsePattern:
    """The structure of an ``(n, n)`` sparse matrix that is a sum of values at fixed
    coordinates ``(rows[j], cols[j])``, sorted once: :meth:`matrix` then fills it with one
    ``bincount`` (scipy's coordinate-to-CSR conversion sorts again at every call).

    Parameters
    ----------
    rows, cols : (p,) int
        Coordinates of the values :meth:`matrix` takes, repeats allowed (they add up).
    n : int
        The matrix is ``(n, n)``.

    Examples
    --------
    >>> P = SparsePattern(np.array([0, 1, 0]), np.array([1, 1, 1]), 2)
    >>> P.matrix(np.array([1.0, 2.0, 3.0])).toarray()
    array([[0., 4.],
           [0., 2.]])
    """

    def __init__(self, rows: np.ndarray, cols: np.ndarray, n: int):
        rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
        if rows.shape != cols.shape or rows.ndim != 1:
            raise ValueError(f"rows and cols must be two (p,) arrays, got {rows.shape} and {cols.shape}")
        if rows.size and (min(rows.min(), cols.min()) < 0 or max(rows.max(), cols.max()) >= n):
            raise ValueError(f"coordinates must lie in [0, {n})")
        keys, self.slot = np.unique(rows * n + cols, return_inverse=True)
        self.slot = self.slot.reshape(-1)
        self.n, self.nnz = int(n), keys.size
        self.indices = (keys % n).astype(np.int32)
        self.indptr = np.zeros(n + 1, dtype=np.int32)
        np.cumsum(np.bincount(keys // n, minlength=n), out=self.indptr[1:])

    def matrix(self, values: np.ndarray) -> sp.csr_matrix:
        """The ``(n, n)`` CSR matrix with ``values (p,)`` summed at their coordinates, in
        canonical form (sorted indices, no repeats)."""
        data = np.bincount(self.slot, weights=values, minlength=self.nnz)
        return self._with(data)

    def _with(self, data: np.ndarray) -> sp.csr_matrix:
        M = sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n, self.n), copy=False)
        M.has_sorted_indices = True
        M.has_canonical_format = True
        return M

    def add(self, M: sp.csr_matrix, other) -> sp.csr_matrix:
        """``M + other`` for ``M`` from :meth:`matrix`: the data arrays added when ``other``
        is a CSR matrix of the same structure, scipy's sum otherwise."""
        if (sp.isspmatrix_csr(other) and other.shape == M.shape and other.nnz == self.nnz
                and np.array_equal(other.indptr, self.indptr)
                and np.array_equal(other.indices, self.indices)):
            return self._with(M.data + other.data)
        return M + other


_CORNER_PAIRS = [(c, d) for c in range(3) for d in range(c, 3)]
_OFF = np.array([c != d for c, d in _CORNER_PAIRS])


def face_corner_pattern(faces: np.ndarray, n: int) -> SparsePattern:
    """The pattern of ``P^T diag(.) P`` (``P`` a closest-point interpolation matrix on the
    triangles ``faces (f, 3)``): every pair of corners of a triangle, both ways, the vertex
    adjacency of the mesh with its diagonal. The values :func:`subspace_normal_equations`
    gives it are the per-face sums ``S (f, 6)`` of the corner pairs ``(c, d)``, ``c <= d``,
    flattened, then the off-diagonal ones again for ``(d, c)``."""
    F = np.asarray(faces, dtype=np.int64)
    first = F[:, [c for c, _ in _CORNER_PAIRS]]
    second = F[:, [d for _, d in _CORNER_PAIRS]]
    rows = np.concatenate([first.ravel(), second[:, _OFF].ravel()])
    cols = np.concatenate([second.ravel(), first[:, _OFF].ravel()])
    return SparsePattern(rows, cols, n)


@dataclass(frozen=True)
class NormalEquations:
    """The Gauss-Newton model of Eq. (3) in the first ``m`` modes, in the layout of
    ``T (m, 3, 4)`` flattened (index ``12 j + 4 a + b``).

    Attributes
    ----------
    A : (12m, 12m) float64
        ``J_z^T W J_z`` (symmetric positive semi-definite).
    g : (12m,) float64
        ``J_z^T W r``, half the gradient of ``E`` with respect to the coefficients.
    """

    A: np.ndarray
    g: np.ndarray

    def predicted_decrease(self, d: np.ndarray) -> float:
        """``E - model(d) = -(2 g.d + d^T A d)`` for a flattened step ``d (12m,)``."""
        return float(-(2.0 * self.g @ d + d @ self.A @ d))


@dataclass(frozen=True)
class VertexBlocks:
    """A term's Gauss-Newton matrix in the vertices, to be added to Eq. (3)'s before the
    products with the skinning matrix (one set of products for both):
    ``sum_(a, a') blocks[a, a']`` on the coordinate blocks ``(a, a')`` (``a <= a'``, each
    ``(n, n)`` sparse, the ``(a', a)`` block its transpose) plus ``sum c (B^T u)(B^T v)^T``
    over ``outer = [(c, u (n, 3), v (n, 3)), ...]`` (``B^T u`` the pulled-back vector).
    """

    blocks: dict
    outer: list

    def subspace(self, basis: LBSBasis, m: int) -> np.ndarray:
        """The matrix alone in the first ``m`` modes, ``(12m, 12m)`` in the T layout."""
        C = basis.skinning_matrix(m)
        A = _assemble({ab: C.T @ (H @ C) for ab, H in self.blocks.items()}, m)
        return _symmetric(A + self.outer_subspace(basis, m))

    def outer_subspace(self, basis: LBSBasis, m: int) -> np.ndarray:
        """The outer products' part alone in the first ``m`` modes, ``sum c (B^T u)(B^T v)^T``,
        ``(12m, 12m)`` in the T layout (not symmetrized)."""
        out = np.zeros((12 * m, 12 * m))
        pulled = {}  # the terms share their vectors: each pulled back once
        for c, u, v in self.outer:
            for x in (u, v):
                if id(x) not in pulled:
                    pulled[id(x)] = basis.pullback(x, m).reshape(-1)
            out += c * np.outer(pulled[id(u)], pulled[id(v)])
        return out


def _symmetric(A: np.ndarray) -> np.ndarray:
    return 0.5 * (A + A.T)


def _assemble(blocks: dict[tuple[int, int], np.ndarray], m: int) -> np.ndarray:
    """Coordinate blocks ``(a, a') -> (4m, 4m)`` to the ``(12m, 12m)`` matrix in T layout."""
    full = np.zeros((m, 3, 4, m, 3, 4))
    for (a, b), blk in blocks.items():
        full[:, a, :, :, b, :] = blk.reshape(m, 4, m, 4)
        if a != b:
            full[:, b, :, :, a, :] = blk.T.reshape(m, 4, m, 4)
    return full.reshape(12 * m, 12 * m)


def subspace_metric(basis: LBSBasis, m: int) -> np.ndarray:
    """``B^T B (12m, 12m)``: ``d^T B^T B d`` is the squared vertex motion of step ``d``.

    Examples
    --------
    >>> import numpy as np
    >>> X0 = np.random.default_rng(1).random((6, 3)); basis = LBSBasis(X0, np.ones((6, 1)))
    >>> d = np.random.default_rng(2).random(12)
    >>> G = subspace_metric(basis, 1)
    >>> bool(np.isclose(d @ G @ d, np.sum(basis.displacement(d.reshape(1, 3, 4)) ** 2)))
    True
    """
    C = basis.skinning_matrix(m)
    CtC = C.T @ C
    return _assemble({(a, a): CtC for a in range(3)}, m)


def subspace_normal_equations(
    evaluation: EnergyEvaluation,
    basis: LBSBasis,
    m: int,
    faces: np.ndarray,
    weights: np.ndarray,
    extra: VertexBlocks | None = None,
    pattern: SparsePattern | None = None,
) -> NormalEquations:
    """Gauss-Newton normal equations of Eq. (3) in the first ``m`` modes.

    Parameters
    ----------
    evaluation : EnergyEvaluation
        An evaluation with its correspondences (``closest_faces``, ``barycentrics``,
        ``normal``), as :meth:`morphmodes_vol.energy.SDFEnergy.evaluate` returns.
    basis : LBSBasis
    m : int
        Active modes.
    faces : (f, 3) int
        Source triangles.
    weights : (k,) float
        Quadrature weights ``w_i``.
    extra : VertexBlocks, optional
        Another term's matrix in the vertices (the isometry prior's), added before the
        products with the skinning matrix; ``g`` is the evaluation's, which holds its
        gradient already.
    pattern : SparsePattern, optional
        ``face_corner_pattern(faces, n)``, built once by a caller that assembles many
        normal equations on one mesh (built here otherwise).

    Returns
    -------
    NormalEquations
    """
    if evaluation.closest_faces is None:
        raise ValueError("the evaluation carries no correspondences (closest_faces is None)")
    n = basis.X0.shape[0]
    t = evaluation.closest_faces
    nf = len(faces)
    if pattern is None:
        pattern = face_corner_pattern(faces, n)
    b, N = evaluation.barycentrics, evaluation.normal
    # per closest face t: S_t[c, d, a, a'] = sum_{i: t_i = t} w_i b_ic b_id n_ia n_ia', the
    # points' contributions gathered by face first (k can be 100x the face count)
    wb = {cd: weights * b[:, cd[0]] * b[:, cd[1]] for cd in _CORNER_PAIRS}
    blocks = {}
    for a in range(3):
        for a2 in range(a, 3):
            nn = N[:, a] * N[:, a2]
            S = np.stack([np.bincount(t, weights=wb[cd] * nn, minlength=nf) for cd in _CORNER_PAIRS], 1)
            # each off-diagonal corner pair (c, d) also stands for (d, c)
            H = pattern.matrix(np.concatenate([S.ravel(), S[:, _OFF].ravel()]))
            if extra is not None and (a, a2) in extra.blocks:
                H = pattern.add(H, extra.blocks[a, a2])
            blocks[a, a2] = H
    # Eq. (3)'s matrix in the vertices, with the other term's folded in, to the subspace
    A = VertexBlocks(blocks=blocks, outer=extra.outer if extra is not None else []).subspace(basis, m)
    g = 0.5 * basis.pullback(evaluation.gradient, m).reshape(-1)  # J_z^T W r = grad / 2
    return NormalEquations(A=A, g=g)


def lm_solve(normal: NormalEquations, metric: np.ndarray, damping: float) -> np.ndarray:
    """Solve ``(A + damping * metric) d = -g``; returns ``d (12m,)``.

    A tiny multiple of the metric's scale is always added, so a mode that no quadrature
    point sees (a zero row of ``A``) gets a zero step instead of a singular system.
    """
    scale = np.trace(normal.A) / max(np.trace(metric), 1e-300)
    lhs = normal.A + (damping + 1e-12) * scale * metric
    try:
        return np.linalg.solve(lhs, -normal.g)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(lhs, -normal.g, rcond=None)[0]


def damping_factor(rho: float) -> float:
    """Nielsen's factor for the damping after an accepted step, ``max(1/3, 1 - (2 rho -
    1)^3)``, ``rho`` the true over the predicted decrease: 1/3 from ``rho = 1`` on, so
    ``rho`` is clipped there (a tiny predicted decrease would overflow the cube).

    Examples
    --------
    >>> damping_factor(0.5), damping_factor(1.0), damping_factor(1e300)
    (1.0, 0.3333333333333333, 0.3333333333333333)
    """
    return max(1.0 / 3.0, 1.0 - (2.0 * min(rho, 1.0) - 1.0) ** 3)
