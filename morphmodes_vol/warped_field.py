"""The warped rest field: Eq. (2) pulled back to the rest pose, minimized without source queries.

Eq. (2) compares the deformed source's signed distance ``f`` with the target's ``g`` at
fixed points ``q``. Substituting ``q = phi(p)``, where ``phi`` carries the space around the
rest source along with it, and taking the deformed source's distance at ``phi(p)`` to be the
rest distance ``f0(p)`` (exact for a rigid motion, and near the surface for a deformation
that bends without stretching much) gives

    E_w(T) = h^3 * sum_p (f0(p) - g(phi_T(p)))^2,                 (pulled-back Eq. 3)
    phi_T(p) = p + sum_j w_j(p) T_j [p 1]                         (Eq. 6 off the surface)

over the nodes ``p`` of a grid of spacing ``h`` within ``band`` of the rest surface, with
``w(p)`` the skinning weights at ``p``'s closest point on the rest surface (the barycentric
mix of its triangle's corners). ``f0`` and ``w`` are computed once, by one closest-point
query of the rest mesh; after that an evaluation is a skinning product and trilinear samples
of the target grid, with no BVH query, and the residual's Jacobian is explicit,
``dr_p / dT_j[a, b] = -d_a g(phi(p)) w_j(p) [p 1]_b`` (``grad g`` by central differences of
the trilinear samples, a quarter spacing apart). The approximation of ``f`` grows
with the distance from the surface (it is exact for rigid motions), so the band is narrow;
the term that is lost is the part of Eq. (2) that asks the target's surface to be covered.
Terms on the vertices (the isometry prior, landmarks) are added as they are.

With ``descriptors`` (docs/method.md, "The stages of a registration"), each node also
compares intrinsic descriptors (:mod:`morphmodes_vol.descriptors`): ``d0(p)``, the rest
source's at ``p``'s closest surface point, with the target's ``d(phi_T(p))`` (each node of a
grid takes the value at its closest target surface point), over ``c`` channels,

    E_w(T) += h^3 * (mu / c) * sum_p ||d0(p) - d(phi_T(p))||^2,

so that a part lands on the part of the target that has its shape, not only on some surface.

:class:`WarpedRestField` builds the field and minimizes ``E_w`` over the subspace, one mode
at a time as Algorithm 1 does, by Levenberg-Marquardt; :meth:`Registration.run` runs it
from every start and refines the best result on Eq. (3) itself (``warped_pass``;
docs/method.md, "The stages of a registration").
"""

from __future__ import annotations

import copy
import logging
import time
from dataclasses import dataclass

import numpy as np

from .eigenbasis.lbs import LBSBasis
from .energy import EnergyEvaluation
from .optimize.gauss_newton import NormalEquations, _assemble, _symmetric, lm_solve, subspace_metric
from .sdf import Grid
from .sdf.source import signed_distance

log = logging.getLogger(__name__)

__all__ = ["WarpedRestField", "WarpedRun", "ZeroEnergy"]


class ZeroEnergy:
    """An energy of value 0 with no quadrature, for :class:`~morphmodes_vol.energy.AddedTerm`
    subclasses to wrap when only their own term is wanted (the ``terms`` of
    :class:`WarpedRestField`)."""

    def __init__(self, n: int):
        self.n = n

    def evaluate(self, X: np.ndarray) -> EnergyEvaluation:
        return EnergyEvaluation(energy=0.0, gradient=np.zeros((self.n, 3)), residual=np.zeros(0))


@dataclass
class WarpedRun:
    """The result of :meth:`WarpedRestField.minimize`.

    Attributes
    ----------
    T : (m, 3, 4) float
        The blocks of every mode (Eq. 5's ``z`` in block form).
    energy : float
        ``E_w`` plus the vertex terms at ``T``.
    evaluations : int
        Evaluations of ``E_w`` (each a skinning product and a trilinear sample, no query).
    steps : int
        Accepted Levenberg-Marquardt steps.
    seconds : float
    stage_energies : (stages,) float
        The energy at the end of each stage: entry ``i`` with ``first_mode + i`` modes.
    damping : float
        Levenberg-Marquardt's damping at the end, to continue with (:meth:`minimize`'s
        ``damping``).
    """

    T: np.ndarray
    energy: float
    evaluations: int
    steps: int
    seconds: float
    stage_energies: np.ndarray
    damping: float

    def then(self, later: "WarpedRun") -> "WarpedRun":
        """This run followed by ``later``, its continuation (:meth:`WarpedRestField.minimize`
        from this run's ``T`` and ``damping``): ``later``'s result, the counts of both."""
        return WarpedRun(T=later.T, energy=later.energy, evaluations=self.evaluations + later.evaluations,
                         steps=self.steps + later.steps, seconds=self.seconds + later.seconds,
                         stage_energies=np.concatenate([self.stage_energies, later.stage_energies]),
                         damping=later.damping)


class WarpedRestField:
    """The rest source's signed distance on a band of grid nodes, carried by the skinning
    subspace (module docstring).

    Parameters
    ----------
    basis : LBSBasis
        The source's subspace: rest vertices ``X0 (n, 3)`` (the frame of ``sample_target``)
        and skinning weights ``W (n, k)`` (the eigenbasis of Eq. 4).
    faces : (f, 3) int
        Source triangles (closed, or with ``sign="winding"``).
    sample_target : callable
        ``g``: points ``(N, 3)`` -> target signed distance ``(N,)`` (trilinear in a grid).
    spacing : float
        ``h``, the grid spacing of the band's nodes (the quadrature's).
    band : float
        Nodes with ``|f0| < band`` are kept (a length; ``2 h`` by :meth:`Registration.run`).
    terms : energy or None
        Vertex terms added to ``E_w`` (the isometry prior, landmarks): an energy with
        ``evaluate(X)`` and optionally ``normal_matrix(basis, m, X)``
        (:class:`~morphmodes_vol.energy.AddedTerm`), built around a :class:`ZeroEnergy` so it
        holds nothing else.
    sign : {"raycast", "winding", "unsigned"}
    samples : int
        Occupancy rays per node (``sign="raycast"``).
    descriptors : (source, sample) or None
        Descriptor channels (module docstring): ``source (n, c)`` at the rest vertices, and
        ``sample``: points ``(N, 3)`` -> the target's ``(N, c)`` (trilinear in a grid of
        :func:`~morphmodes_vol.descriptors.surface_descriptor_grid`).
    descriptor_weight : float
        ``mu``, the weight of the channels' mean squared residual against the SDF's.
    sample_weight : callable or None
        Points ``(N, 3)`` -> a weight ``(N,)`` of each node's terms at its place ``phi_T(p)``:
        an open target's confidence (:mod:`morphmodes_vol.sdf.confidence`), held fixed in
        the Gauss-Newton model.

    Examples
    --------
    >>> from morphmodes_vol.primitives import icosphere
    >>> V, F = icosphere(3)
    >>> W = np.ones((len(V), 1))
    >>> field = WarpedRestField(LBSBasis(V, W), F, lambda q: np.linalg.norm(q - [0.2, 0, 0], axis=1) - 1,
    ...                         spacing=0.1, band=0.2)
    >>> run = field.minimize(np.zeros((1, 3, 4)), modes=1)
    >>> np.round(run.T[0, :, 3] / W[0, 0], 2)  # the translation found
    array([ 0.2, -0. , -0. ])
    """

    def __init__(self, basis: LBSBasis, faces: np.ndarray, sample_target, spacing: float,
                 band: float, terms=None, sign: str = "raycast", samples: int = 1,
                 descriptors=None, descriptor_weight: float = 0.0, sample_weight=None):
        if not (spacing > 0 and band > 0):
            raise ValueError(f"spacing and band must be positive, got {spacing} and {band}")
        t = time.perf_counter()
        X0 = basis.X0
        lo, hi = X0.min(0) - band, X0.max(0) + band
        grid = Grid.covering(lo, hi, int(np.ceil(np.max(hi - lo) / spacing)) + 1)
        P = grid.points()
        q = signed_distance(X0, faces, P, sign=sign, samples=samples)
        near = np.abs(q.value) < band
        if not near.any():
            raise ValueError("no grid node lies within the band of the rest surface; "
                             "the spacing is too coarse for the mesh")
        # each node's closest rest surface point: its triangle's corners and barycentrics
        self._corners = np.asarray(faces)[q.closest.faces[near]]
        self._barycentrics = q.closest.barycentrics[near]
        W = self._at_closest(basis.W)
        self.d0 = self.sample_descriptors = None
        self._channel_weight = 0.0  # mu / c
        self.points = P[near]
        self.f0 = q.value[near]
        self.cell_volume = grid.cell_volume
        self.nodes_queried = P.shape[0]
        self.point_basis = LBSBasis(self.points, W)
        self.basis = basis
        self.sample_target = sample_target
        self.sample_weight = sample_weight
        self._step = 0.25 * spacing  # central differences of g inside a trilinear cell
        self.terms = terms
        self.evaluations = 0
        if descriptors is not None:
            self._set_descriptors(descriptors, descriptor_weight)
        self.build_seconds = time.perf_counter() - t
        log.info("warped rest field: %d band nodes of %d (%.2f s)", len(self.points),
                 self.nodes_queried, self.build_seconds)

    def _at_closest(self, values: np.ndarray) -> np.ndarray:
        """Per-vertex ``values (n, k)`` of the rest mesh at each node's closest surface point
        (the barycentric mix of its triangle's corners), ``(N, k)``."""
        return np.einsum("pc,pcj->pj", self._barycentrics, values[self._corners])

    def _sampled(self, sample, Y: np.ndarray, gradient: bool):
        """``sample(Y)`` (``(N,)`` or ``(N, c)``) and, with ``gradient``, its gradient
        (``(N, 3)`` or ``(N, c, 3)``) by central differences a step apart inside a trilinear
        cell, from one call on the 7 stacked point sets."""
        if not gradient:
            return sample(Y), None
        offsets = np.vstack([np.zeros(3), np.eye(3) * self._step, -np.eye(3) * self._step])  # (7, 3)
        values = np.asarray(sample((Y[None] + offsets[:, None]).reshape(-1, 3)))
        s = values.reshape(7, len(Y), -1)
        G = ((s[1:4] - s[4:7]) / (2 * self._step)).transpose(1, 2, 0)  # (N, c, 3)
        if values.ndim == 1:  # one channel, as given
            return s[0, :, 0], G[:, 0]
        return s[0], G

    def _set_descriptors(self, descriptors, weight: float) -> None:
        D = np.asarray(descriptors[0], dtype=np.float64)
        if D.ndim != 2 or D.shape[0] != self.basis.X0.shape[0]:
            raise ValueError(f"source descriptors must be (n, c) with n = {self.basis.X0.shape[0]} "
                             f"vertices, got {D.shape}")
        if not weight >= 0:
            raise ValueError(f"descriptor_weight must be non-negative, got {weight}")
        self.d0 = self._at_closest(D)
        self.sample_descriptors = descriptors[1]
        self._channel_weight = float(weight) / D.shape[1]

    def with_descriptors(self, descriptors, descriptor_weight: float) -> "WarpedRestField":
        """This field with descriptor channels (``descriptors`` and ``descriptor_weight`` as
        in the constructor): the same band nodes, no new query; its own evaluation count."""
        out = copy.copy(self)
        out.evaluations = 0
        out._set_descriptors(descriptors, descriptor_weight)
        return out

    def evaluate(self, T: np.ndarray, m: int | None = None):
        """``E_w`` plus the vertex terms at the blocks ``T (k, 3, 4)``; with ``m``, also the
        Gauss-Newton normal equations in the first ``m`` modes (``NormalEquations``, ``g``
        half the gradient, as :mod:`morphmodes_vol.optimize.gauss_newton` uses).

        Returns
        -------
        float, or (float, NormalEquations) when ``m`` is given
        """
        self.evaluations += 1
        Y = self.point_basis.deform(T)
        g, G = self._sampled(self.sample_target, Y, m is not None)
        r = self.f0 - g
        # the nodes' weights: the cell volume, times an open target's confidence there
        v = self.cell_volume if self.sample_weight is None else self.cell_volume * self.sample_weight(Y)
        E = float(np.sum(v * r * r))
        if self.d0 is not None:
            d, Gd = self._sampled(self.sample_descriptors, Y, m is not None)
            rd = self.d0 - d
            E += self._channel_weight * float(np.sum(v * np.sum(rd * rd, axis=1)))
        X = self.basis.deform(T) if self.terms is not None else None
        ev = self.terms.evaluate(X) if self.terms is not None else None
        if ev is not None:
            E += ev.energy
        if m is None:
            return E
        C = self.point_basis.skinning_matrix(m)
        v = np.broadcast_to(v, r.shape)  # per node, for the products below
        if self.d0 is None:
            GG = {(a, b): v * G[:, a] * G[:, b] for a in range(3) for b in range(a, 3)}
            RG = v[:, None] * r[:, None] * G
        else:  # the channels' rows, weighted, summed per node before the products with C
            mu = self._channel_weight
            GG = {(a, b): v * (G[:, a] * G[:, b] + mu * np.einsum("pj,pj->p", Gd[:, :, a], Gd[:, :, b]))
                  for a in range(3) for b in range(a, 3)}
            RG = v[:, None] * (r[:, None] * G + mu * np.einsum("pj,pja->pa", rd, Gd))
        blocks = {ab: C.T @ (C * w[:, None]) for ab, w in GG.items()}
        A = _assemble(blocks, m)
        # J^T W r with J = -G (x) C: (4m, 3) in (mode, column) x coordinate, to the T layout
        half_gradient = -(C.T @ RG).reshape(m, 4, 3).transpose(0, 2, 1).ravel()
        if ev is not None:
            half_gradient = half_gradient + 0.5 * self.basis.pullback(ev.gradient, m).ravel()
            # every term's Gauss-Newton block, the vertex-block ones included (not folded)
            normal_matrix = getattr(self.terms, "normal_matrix", None)
            other = None if normal_matrix is None else normal_matrix(self.basis, m, X)
            if other is not None:
                A = A + other
        return E, NormalEquations(A=_symmetric(A), g=half_gradient)

    def minimize(self, T0: np.ndarray, modes: int, iterations_per_stage: int = 5,
                 stall_decrease: float = 1e-3, damping: float = 1e-3, first_mode: int = 1,
                 start_damping: float | None = None) -> WarpedRun:
        """Minimize ``E_w`` from ``T0 (k, 3, 4)``, adding one mode per stage from
        ``first_mode`` up to ``modes`` (Algorithm 1's schedule), each stage by at most
        ``iterations_per_stage`` Levenberg-Marquardt steps (damping in the metric of the
        vertex motion, as :func:`~morphmodes_vol.optimize.gauss_newton.lm_solve`, from
        ``start_damping`` (default ``damping``), back to ``damping`` when no step is
        accepted); a stage ends when a step lowers the energy by less than the fraction
        ``stall_decrease``. ``run.then(minimize(run.T, M, first_mode=m + 1,
        start_damping=run.damping))`` continues a run of ``m`` modes as if it had not stopped."""
        if not 1 <= first_mode <= modes:
            raise ValueError(f"first_mode must lie in [1, modes={modes}], got {first_mode}")
        t = time.perf_counter()
        before = self.evaluations
        T = np.zeros((modes, 3, 4))
        k = min(len(T0), modes)
        T[:k] = np.asarray(T0, dtype=np.float64)[:k]
        lam = damping if start_damping is None else start_damping
        steps, E, stages = 0, float("nan"), []
        for m in range(first_mode, modes + 1):
            metric = subspace_metric(self.basis, m)
            E, normal = self.evaluate(T, m)
            for iteration in range(iterations_per_stage):
                accepted = False
                while lam <= 1e8:
                    trial = T.copy()
                    trial[:m] += lm_solve(normal, metric, lam).reshape(m, 3, 4)
                    E_trial = self.evaluate(trial)
                    if E_trial < E:
                        accepted = True
                        lam = max(lam / 3.0, 1e-9)
                        break
                    lam *= 4.0
                if not accepted:
                    lam = damping
                    break
                decrease = (E - E_trial) / max(E, 1e-300)
                T, E, steps = trial, E_trial, steps + 1
                if decrease < stall_decrease or iteration == iterations_per_stage - 1:
                    break  # the stage ends: no model at T in these m modes is needed
                _, normal = self.evaluate(T, m)
            stages.append(E)
        return WarpedRun(T=T, energy=E, evaluations=self.evaluations - before, steps=steps,
                         seconds=time.perf_counter() - t, stage_energies=np.array(stages), damping=lam)
