"""The SDF matching energy, Eq. (2)-(3), and its gradients.

    E(x) = h^3 * sum_i (f(Q_i; x) - g(Q_i))^2

(more generally ``sum_i w_i (f_i - g_i)^2`` with per-point quadrature weights ``w_i``).

``f`` is the signed distance of the deformed source, ``g`` the target's, ``Q`` the
quadrature points (nodes of a regular grid of spacing ``h``). The factor ``h^3`` makes ``E``
a quadrature of the integral of Eq. (2), so energies compare across grid resolutions; it
does not change the minimizer of Eq. (3).

Gradient with respect to the vertices: with ``p_i = sum_c b_ic v_{t_i c}`` the closest point
of ``Q_i`` (triangle ``t_i``, barycentrics ``b_i``) and ``n_i = grad_q f(Q_i)``,
``df_i/dv_{t_i c} = -b_ic n_i`` (the motion of ``p_i`` within the surface does not change the
distance to first order), so

    dE/dv_j = -2 h^3 sum_{i, c: t_ic = j} (f_i - g_i) b_ic n_i.

With respect to the subspace coefficients it is ``B^T dE/dx`` (Algorithm 1), see
:meth:`morphmodes_vol.eigenbasis.LBSBasis.pullback`.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from .sdf.source import DistanceSign, signed_distance

__all__ = ["SDFEnergy", "EnergyEvaluation", "AddedTerm"]


@dataclass(frozen=True)
class EnergyEvaluation:
    """One evaluation of the energy at a vertex configuration.

    Attributes
    ----------
    energy : float
    gradient : (n, 3) float64
        ``dE/dx`` per vertex.
    residual : (k,) float64
        ``f - g`` at the quadrature points.
    closest_faces : (k,) int64, optional
        Source triangle closest to each quadrature point.
    barycentrics : (k, 3) float64, optional
        Barycentric coordinates of the closest point on that triangle.
    normal : (k, 3) float64, optional
        ``grad_q f`` at each quadrature point. With the two above, the Jacobian of the
        residual with respect to the vertices (frozen correspondences, see
        :mod:`morphmodes_vol.optimize.gauss_newton`).
    volume : float, optional
        Sum of the quadrature weights (the volume the points stand for).
    extra_energy : float
        The part of ``energy`` that is not Eq. (3): terms added to it (landmarks,
        :mod:`morphmodes_vol.landmarks`; the isometry prior, :mod:`morphmodes_vol.isometry`).
        ``0`` for Eq. (3) alone.
    """

    energy: float
    gradient: np.ndarray
    residual: np.ndarray
    closest_faces: np.ndarray | None = None
    barycentrics: np.ndarray | None = None
    normal: np.ndarray | None = None

    volume: float | None = None
    extra_energy: float = 0.0

    @property
    def rms_residual(self) -> float:
        """Root mean square of ``f - g`` over the quadrature's volume,
        ``sqrt(E / sum_i w_i)`` (normalized length units, ``E`` without ``extra_energy``):
        on a regular grid the plain RMS over the nodes, and comparable across quadratures
        of the same box."""
        if self.volume is None:
            return float(np.sqrt(np.mean(self.residual**2)))
        return float(np.sqrt(max(self.energy - self.extra_energy, 0.0) / self.volume))


class SDFEnergy:
    """Eq. (3) for a fixed source connectivity, quadrature and target values.

    Parameters
    ----------
    F : (m, 3) int
        Source triangles, oriented outward where they enclose a volume (as the registration
        makes them, :func:`morphmodes_vol.repair.sdf_faces`): the source's SDF follows their
        orientation (``oriented`` of :func:`~morphmodes_vol.sdf.signed_distance`), so a
        deformation that turns a closed source inside out does not fit a target as well as
        the same surface the right way out (docs/decisions/0017).
    Q : (k, 3) float
        Quadrature points.
    g : (k,) float
        Target signed distance at ``Q``.
    weight : float or (k,) float
        Quadrature weight of every point (``h^3`` on a regular grid).
    sign : {"raycast", "winding", "unsigned"}
        Inside test of the deformed source; ``"unsigned"``: none (``g`` unsigned too).
    samples : int
        Rays of the ray-parity inside test.

    Examples
    --------
    >>> import numpy as np, trimesh
    >>> from morphmodes_vol.sdf import Grid, signed_distance
    >>> s = trimesh.creation.icosphere(2)
    >>> grid = Grid.covering([-1.5] * 3, [1.5] * 3, 9)
    >>> Q = grid.points()
    >>> g = signed_distance(s.vertices, s.faces, Q).value
    >>> E = SDFEnergy(s.faces, Q, g, grid.cell_volume)
    >>> float(E.evaluate(np.asarray(s.vertices)).energy) < 1e-20
    True
    """

    def __init__(self, F, Q, g, weight: float, sign: DistanceSign = "raycast", samples: int = 1):
        self.F = np.ascontiguousarray(F, dtype=np.int64)
        self.Q = np.ascontiguousarray(Q, dtype=np.float64)
        self.g = np.ascontiguousarray(g, dtype=np.float64)
        if self.g.shape != (self.Q.shape[0],):
            raise ValueError(f"g must have shape ({self.Q.shape[0]},), got {self.g.shape}")
        w = np.asarray(weight, dtype=np.float64)
        if w.ndim == 0:
            w = np.full(self.Q.shape[0], float(w))
        if w.shape != (self.Q.shape[0],) or not np.all(np.isfinite(w)) or np.any(w < 0):
            raise ValueError(f"weight must be a non-negative scalar or ({self.Q.shape[0]},) array")
        self.weights = w
        self.sign: DistanceSign = sign
        self.samples = int(samples)
        self.evaluations = 0
        self.points_queried = 0
        self.seconds = 0.0

    def evaluate(self, X: np.ndarray) -> EnergyEvaluation:
        """Energy and vertex gradient at vertices ``X (n, 3)``."""
        t0 = time.perf_counter()
        sd = signed_distance(X, self.F, self.Q, sign=self.sign, samples=self.samples, oriented=True)
        value, faces, bary, normal = sd.value, sd.closest.faces, sd.closest.barycentrics, sd.normal
        self.points_queried += len(value)
        r = value - self.g
        wr = self.weights * r
        energy = float(wr @ r)
        # dE/dv for the three corners of each closest triangle, scattered to vertices
        coef = (-2.0 * wr)[:, None] * bary  # (k, 3)
        tri = self.F[faces]  # (k, 3)
        n = X.shape[0]
        grad = np.empty((n, 3))
        idx = tri.ravel()
        for d in range(3):
            contrib = (coef * normal[:, d : d + 1]).ravel()
            grad[:, d] = np.bincount(idx, weights=contrib, minlength=n)
        self.evaluations += 1
        self.seconds += time.perf_counter() - t0
        return EnergyEvaluation(
            energy=energy,
            gradient=grad,
            residual=r,
            closest_faces=faces,
            barycentrics=bary,
            normal=normal,
            volume=float(self.weights.sum()),
        )


class AddedTerm:
    """Base of a term added to an energy with the interface of :class:`SDFEnergy`
    (``evaluate``, ``F``, ``weights``, ``evaluations``,
    ``seconds``), so the optimizers of :mod:`morphmodes_vol.optimize` see no difference.

    A subclass defines :meth:`term` (its value and vertex gradient) and
    :meth:`term_normal_matrix` (its Gauss-Newton block in the active subspace, as
    :mod:`morphmodes_vol.optimize.gauss_newton` lays it out); :meth:`evaluate` adds the value
    to ``energy`` and ``extra_energy`` (so ``rms_residual`` stays Eq. 3's) and
    :meth:`normal_matrix` adds the inner energy's block when it has one. Used by the
    landmarks (:mod:`morphmodes_vol.landmarks`) and the isometry prior
    (:mod:`morphmodes_vol.isometry`).
    """

    #: whether :meth:`term_vertex_blocks` returns the term's matrix (a subclass that
    #: defines it sets this), so :meth:`normal_matrix` knows what the optimizer folds
    has_vertex_blocks = False

    def __init__(self, inner):
        self.inner = inner

    # the optimizer reads these from the energy it is given
    F = property(lambda self: self.inner.F)
    weights = property(lambda self: self.inner.weights)
    evaluations = property(lambda self: self.inner.evaluations)
    seconds = property(lambda self: self.inner.seconds)
    points_queried = property(lambda self: self.inner.points_queried)

    def term(self, X: np.ndarray) -> tuple[float, np.ndarray]:
        """The term's value and its vertex gradient ``(n, 3)`` at ``X (n, 3)``."""
        raise NotImplementedError

    def term_normal_matrix(self, basis, m: int, X: np.ndarray | None) -> np.ndarray:
        """The term's Gauss-Newton block ``(12m, 12m)`` at ``X (n, 3)`` in the first ``m`` modes."""
        raise NotImplementedError

    def term_vertex_blocks(self, X: np.ndarray):
        """The term's Gauss-Newton matrix in the vertices
        (:class:`~morphmodes_vol.optimize.gauss_newton.VertexBlocks`), when it has that form,
        so the optimizer can add it to Eq. (3)'s before the products with the skinning
        matrix; ``None`` (default): only :meth:`term_normal_matrix`."""
        return None

    def vertex_blocks(self, X: np.ndarray):
        """The vertex-space matrices of this term and the inner ones, merged (``None`` if
        none has one); :meth:`normal_matrix` with ``folded=True`` leaves them out."""
        own = self.term_vertex_blocks(X)
        inner = getattr(self.inner, "vertex_blocks", None)
        other = inner(X) if inner is not None else None
        if own is None or other is None:
            return own if other is None else other
        blocks = dict(other.blocks)
        for ab, H in own.blocks.items():
            blocks[ab] = blocks[ab] + H if ab in blocks else H
        return type(own)(blocks=blocks, outer=list(other.outer) + list(own.outer))

    def _evaluation(self, total: EnergyEvaluation, value: float) -> EnergyEvaluation:
        """The evaluation to return; a subclass may add fields (``value``: the term's)."""
        return total

    def evaluate(self, X: np.ndarray) -> EnergyEvaluation:
        """The inner energy plus the term, and the vertex gradient, at ``X (n, 3)``."""
        ev = self.inner.evaluate(X)
        value, grad = self.term(X)
        total = dataclasses.replace(ev, energy=ev.energy + value, gradient=ev.gradient + grad,
                                    extra_energy=ev.extra_energy + value)
        return self._evaluation(total, value)

    def normal_matrix(self, basis, m: int, X: np.ndarray | None = None,
                      folded: bool = False) -> np.ndarray | None:
        """The term's Gauss-Newton block plus the inner energy's, when it has one.
        ``folded``: without the terms that have vertex blocks (:meth:`vertex_blocks`, which
        the optimizer folds into Eq. 3's); ``None`` when nothing is left."""
        A = None if folded and self.has_vertex_blocks else self.term_normal_matrix(basis, m, X)
        inner = getattr(self.inner, "normal_matrix", None)
        B = None if inner is None else inner(basis, m, X, folded=folded)
        if A is None or B is None:
            return A if B is None else B
        return A + B
