"""The isometry prior (on by default): a penalty on the uneven stretch of the source's edges, added to Eq. (3).

The paper's energy (Eq. 3) only asks the deformed source's SDF to match the target's; the
skinning subspace is its only regularizer. A body in another pose is close to an isometry of
itself, and registrations that fit the SDF with wrong correspondences stretch the surface
unevenly. This term penalizes that, without fixing the overall size:

    rho_e = log(l_e / L_e),   r_e = rho_e - sum_k a_k rho_k,
    h(r) = sign(r) max(|r| - tol, 0),
    E_iso(x) = weight * V * sum_e a_e h(r_e)^2,

``l_e = |x_i - x_j|`` the deformed and ``L_e`` the rest length of edge ``e = (i, j)``, ``a_e``
its share of the rest surface area (a third of the area of each triangle it bounds, so
``sum_e a_e = 1`` and the sum approximates a surface integral whatever the meshing), ``V``
the volume of the quadrature box (the sum of Eq. 3's weights) and ``tol`` a tolerance: an
edge whose log stretch is within ``tol`` of the mean costs nothing, so moderate stretch (a
limb bending, a shape 20% longer) is left to the SDF term and only the large, uneven
stretch of wrong correspondences is penalized. With ``tol = 0``, ``E_iso / V`` is ``weight``
times the area-weighted variance of the log stretch (:func:`log_stretch_variance`);
``E_sdf / V`` is the mean squared SDF residual over the box (normalized units: the union
bounding box has diagonal 1). Unit of ``weight``: squared normalized length; with
``weight = 3e-4`` an excess log stretch ``s`` everywhere costs as much as an SDF residual of
``0.017 s`` of the diagonal everywhere. The term is zero for any similarity (rigid motion
and uniform scale) of the rest pose, so the affine first stage may still scale the source.

Gradient: ``dE/drho = 2 weight V P^T (a h)``, ``P = I - 1 a^T`` the removal of the weighted
mean, and ``drho_e/dx_i = (x_i - x_j) / l_e^2``. Gauss-Newton block (half the Hessian of the
linearized residuals, as :mod:`morphmodes_vol.optimize.gauss_newton` uses): with ``J =
drho/dz`` in the active subspace and ``d = a`` on the edges beyond the tolerance (0 elsewhere),
``weight V J^T P^T diag(d) P J = weight V (J^T diag(d) J - va vd^T - vd va^T + (sum d) va
va^T)``, ``va = J^T a``, ``vd = J^T d``. ``J = J_x B``, so the term hands the optimizer its
matrix in the vertices (:meth:`IsometryEnergy.term_vertex_blocks`), which joins Eq. (3)'s
before the products with the skinning matrix ``B``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .energy import AddedTerm
from .metrics import triangle_areas
from .optimize.gauss_newton import SparsePattern, VertexBlocks, _assemble, _symmetric

__all__ = ["IsometryEnergy", "edge_area_shares", "log_stretch_variance"]


def edge_area_shares(V0, F) -> tuple[np.ndarray, np.ndarray]:
    """Every edge of the triangles once and its share of their area.

    Parameters
    ----------
    V0 : (n, 3) float
    F : (f, 3) int

    Returns
    -------
    edges : (E, 2) int64
        Vertex pairs, smaller index first, edges of zero length or zero share left out.
    shares : (E,) float64
        A third of the area of each triangle the edge bounds, normalized to sum to 1.

    Examples
    --------
    >>> V0 = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    >>> edges, shares = edge_area_shares(V0, [[0, 1, 2], [1, 3, 2]])
    >>> edges.tolist()
    [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]
    >>> np.round(shares * 6, 6).tolist()   # the diagonal (1, 2) bounds both triangles
    [1.0, 1.0, 2.0, 1.0, 1.0]
    """
    V0 = np.asarray(V0, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    edges, inverse = np.unique(np.sort(e, axis=1), axis=0, return_inverse=True)
    area = triangle_areas(V0, F)
    share = np.bincount(inverse.ravel(), weights=np.tile(area / 3.0, 3), minlength=len(edges))
    length = np.linalg.norm(V0[edges[:, 0]] - V0[edges[:, 1]], axis=1)
    keep = (length > 0) & (share > 0)
    if not keep.any():
        raise ValueError("the mesh has no edge of positive length bounding a triangle of positive area")
    return edges[keep], share[keep] / share[keep].sum()


def log_stretch_variance(V0, V, F) -> float:
    """Area-weighted variance of ``log(l / L)`` over the edges of ``F`` from ``V0 (n, 3)``
    to ``V (n, 3)``: ``E_iso / (weight V)`` of the module docstring. 0 for a similarity.

    Examples
    --------
    >>> V0 = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0]]); F = [[0, 1, 2]]
    >>> log_stretch_variance(V0, 3 * V0 + 1, F) < 1e-30     # a uniform scale and a shift
    True
    >>> round(log_stretch_variance(V0, V0 * [2, 1, 1], F), 6)  # var(log 2, 0, log sqrt(5/2))
    0.082842
    """
    edges, shares = edge_area_shares(V0, F)
    V0, V = np.asarray(V0, dtype=np.float64), np.asarray(V, dtype=np.float64)
    rest = np.linalg.norm(V0[edges[:, 0]] - V0[edges[:, 1]], axis=1)
    rho = np.log(np.maximum(np.linalg.norm(V[edges[:, 0]] - V[edges[:, 1]], axis=1), 1e-12 * rest) / rest)
    r = rho - shares @ rho
    return float(shares @ (r * r))


class IsometryEnergy(AddedTerm):
    """``E_inner + E_iso`` with the interface of :class:`~morphmodes_vol.energy.SDFEnergy`
    (:class:`~morphmodes_vol.energy.AddedTerm`) and a Gauss-Newton block for the
    Levenberg-Marquardt step.

    Parameters
    ----------
    inner : SDFEnergy or another energy with that interface
    X0 : (n, 3) float
        Rest pose (normalized frame).
    faces : (f, 3) int
        Source triangles.
    weight : float
        ``weight`` of the module docstring (squared normalized length), positive.
    volume : float
        Volume of the quadrature box, ``V``.
    tolerance : float
        ``tol`` of the module docstring (0: the variance of the log stretch).

    Examples
    --------
    >>> from morphmodes_vol.energy import SDFEnergy
    >>> from morphmodes_vol.primitives import icosphere
    >>> V, F = icosphere(1)
    >>> sdf = SDFEnergy(F, np.zeros((1, 3)), np.array([-1.0]), 1.0)
    >>> E = IsometryEnergy(sdf, V, F, weight=2.0, volume=1.0)
    >>> float(E.evaluate(2 * V).extra_energy) < 1e-25     # no cost for a uniform scale
    True
    >>> round(E.evaluate(V * [1.5, 1, 1]).extra_energy / log_stretch_variance(V, V * [1.5, 1, 1], F), 9)
    2.0
    """

    has_vertex_blocks = True

    def __init__(self, inner, X0, faces, weight: float, volume: float, tolerance: float = 0.0):
        super().__init__(inner)
        self.tolerance = float(tolerance)
        X0 = np.asarray(X0, dtype=np.float64)
        self.edges, self.shares = edge_area_shares(X0, faces)
        self.rest = np.linalg.norm(X0[self.edges[:, 0]] - X0[self.edges[:, 1]], axis=1)
        self.n = X0.shape[0]
        self.coefficient = float(weight) * float(volume)
        e = len(self.edges)
        p, q = self.edges[:, 0], self.edges[:, 1]
        # pattern of D^T diag(w) D (D the edge-vertex incidence): a weighted graph Laplacian
        self._pattern = SparsePattern(np.r_[p, q, p, q], np.r_[p, q, q, p], self.n)
        self._incidence = sp.csr_matrix((np.r_[np.ones(e), -np.ones(e)], (np.r_[np.arange(e), np.arange(e)],
                                                                           np.r_[p, q])), shape=(e, self.n))
        self._last = None  # (X, stretch(X)) of the last call

    def stretch(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Penalized residuals ``h(r) (E,)`` (``r`` beyond the tolerance), the mask of edges
        beyond it ``(E,)`` and ``drho_e/dx_i = (x_i - x_j) / l_e^2`` ``(E, 3)``. An
        optimizer's step asks for the term and then its matrix at the same vertices: the last
        call's arrays (read-only) are kept for a call with equal ``X``."""
        last = self._last  # read once: another thread may replace it
        if last is not None and np.array_equal(last[0], X):
            return last[1]
        d = X[self.edges[:, 0]] - X[self.edges[:, 1]]
        length = np.maximum(np.linalg.norm(d, axis=1), 1e-12 * self.rest)
        rho = np.log(length / self.rest)
        r = rho - self.shares @ rho
        active = np.abs(r) > self.tolerance
        out = (np.where(active, r - np.sign(r) * self.tolerance, 0.0), active, d / (length**2)[:, None])
        for a in out:
            a.flags.writeable = False
        self._last = (np.array(X, copy=True), out)
        return out

    def term(self, X: np.ndarray) -> tuple[float, np.ndarray]:
        """``E_iso`` and its vertex gradient ``(n, 3)`` at ``X (n, 3)``."""
        h, _, drho = self.stretch(np.asarray(X, dtype=np.float64))
        ah = self.shares * h
        # dE/drho = 2 c P^T (a h), P = I - 1 a^T the removal of the weighted mean
        g_rho = 2.0 * self.coefficient * (ah - self.shares * ah.sum())
        # D^T (g_rho drho): + on each edge's first vertex, - on its second
        grad = np.asarray(self._incidence.T @ (g_rho[:, None] * drho))
        return self.coefficient * float(ah @ h), grad

    def term_vertex_blocks(self, X: np.ndarray) -> VertexBlocks:
        """The term's Gauss-Newton matrix in the vertices at ``X (n, 3)`` (module docstring):
        ``J^T P^T diag(d) P J = J^T diag(d) J - va vd^T - vd va^T + (sum d) va va^T``, the
        first part as sparse coordinate blocks, the others as outer products."""
        _, active, drho = self.stretch(np.asarray(X, dtype=np.float64))
        dw = self.shares * active  # diag(d) of the edges beyond the tolerance
        c = self.coefficient
        blocks = {}
        for i in range(3):
            for j in range(i, 3):
                w = c * dw * drho[:, i] * drho[:, j]
                blocks[i, j] = self._pattern.matrix(np.r_[w, w, -w, -w])
        return VertexBlocks(blocks=blocks, outer=self._outer_terms(dw, drho))

    def _outer_terms(self, dw: np.ndarray, drho: np.ndarray) -> list:
        """The matrix's outer products (module docstring), ``- va vd^T - vd va^T + (sum d) va
        va^T`` times the coefficient, as the ``(c, u, v)`` of :class:`VertexBlocks`, from
        ``d`` (``dw (E,)``, zero on the edges within the tolerance) and ``drho (E, 3)``."""
        c = self.coefficient

        def vertex(weights):  # D^T (weights * drho), (n, 3): J^T weights before B^T
            return np.stack([self._incidence.T @ (weights * drho[:, i]) for i in range(3)], axis=1)

        ua, ud = vertex(self.shares), vertex(dw)
        return [(-c, ua, ud), (-c, ud, ua), (c * dw.sum(), ua, ua)]

    def term_normal_matrix(self, basis, m: int, X: np.ndarray) -> np.ndarray:
        """The term's Gauss-Newton block at the vertices ``X (n, 3)`` in the first ``m``
        modes, ``(12m, 12m)`` in the T layout of
        :class:`~morphmodes_vol.optimize.gauss_newton.NormalEquations` (module docstring).

        The matrix of ``term_vertex_blocks(X).subspace(basis, m)``, computed on the edges
        beyond the tolerance only: ``C^T D^T diag(w) D C = K^T diag(w) K`` with ``K = D C``
        the differences of the skinning matrix ``C`` across those edges (``D`` the
        edge-vertex incidence, ``w`` zero on the other edges), so neither the sparse
        ``(n, n)`` blocks nor their products with ``C`` are formed. On the lion's warped
        rest field, 7-20% of the edges are beyond the tolerance; the same matrix to
        rounding (tested)."""
        _, active, drho = self.stretch(np.asarray(X, dtype=np.float64))
        c = self.coefficient
        dw = self.shares * active
        C = basis.skinning_matrix(m)
        on = np.flatnonzero(active)
        K = C[self.edges[on, 0]] - C[self.edges[on, 1]]  # D C on the active edges, (k, 4m)
        blocks = {}
        for i in range(3):
            for j in range(i, 3):
                blocks[i, j] = K.T @ (K * (c * dw[on] * drho[on, i] * drho[on, j])[:, None])
        outer = VertexBlocks(blocks={}, outer=self._outer_terms(dw, drho))
        return _symmetric(_assemble(blocks, m) + outer.outer_subspace(basis, m))
