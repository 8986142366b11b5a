"""Algorithm 1: optimization in an adaptive skinning-eigenmode subspace.

Start with one mode (a global affine map); take steps on the coefficients of the active
modes; when one step moves the vertices by less than ``eps_stall`` (root-mean-square vertex
motion, normalized units), or a stage's step cap is reached, add the next mode (12 more
coefficients, started at zero); stop after ``m_max`` modes.

Two steps share this schedule:

- ``optimizer="paper"`` (default): the paper's gradient step with a backtracking (Armijo) line search.
  Deviation (docs/method.md): by default each mode's 3x4 block of the gradient is multiplied
  by the inverse of its 4x4 Gram matrix ``[X0 1]^T diag(w_j)^2 [X0 1]``; plain gradient
  descent on the raw coefficients is badly conditioned (translation and linear parts of a
  block differ in scale by ~25x on the lion); ``preconditioner="none"`` gives the paper's
  plain step.
- ``optimizer="lm"`` (the fast path): a Levenberg-Marquardt step on the Gauss-Newton model with
  frozen correspondences (:mod:`.gauss_newton`), accepted on the true energy.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable, Literal

import numpy as np

from ..blas import single_threaded_blas
from ..eigenbasis.lbs import LBSBasis
from ..energy import EnergyEvaluation, SDFEnergy
from ..errors import OptionError
from ..options import OPTIMIZERS, PRECONDITIONERS, RegistrationOptions
from .gauss_newton import (NormalEquations, damping_factor, face_corner_pattern, lm_solve, subspace_metric,
                           subspace_normal_equations)
from .linesearch import armijo_backtracking

__all__ = ["optimize_adaptive", "AdaptiveRun", "single_threaded_blas", "OptimizationHistory", "ProgressEvent",
           "Status"]

log = logging.getLogger(__name__)

Status = Literal["converged", "stage_cap", "max_iterations", "rolled_back"]
StageEnd = Literal["stalled", "line_search", "iteration_cap", "max_iterations", "fault"]


@dataclass(frozen=True)
class ProgressEvent:
    """What a progress display needs after every accepted step (or stage change)."""

    modes: int
    max_modes: int
    iteration: int
    stage_iteration: int
    energy: float
    step_rms: float
    threshold: float
    evaluations: int
    elapsed: float
    start: str = ""  # which start, when a registration runs several (``rest``, ``aligned``)


@dataclass
class OptimizationHistory:
    """Per-iteration record of a run.

    Attributes
    ----------
    energy : list of float
        Energy after every accepted step; ``energy[0]`` is the initial energy.
    step_rms : list of float
        RMS vertex motion of each accepted step (``len(energy) - 1`` entries).
    modes : list of int
        Active modes at each accepted step.
    stage_starts : list of int
        Index into ``step_rms`` where each stage (1, 2, ... modes) began.
    stage_ends : list of str
        Why each stage ended: ``stalled``, ``line_search``, ``iteration_cap``,
        ``max_iterations``, ``fault`` (a NaN or infinite energy or gradient blocked
        progress; the run stops there).
    stage_seconds : list of float
        Wall time of each stage.
    stage_evaluations : list of int
        Source-SDF evaluations spent in each stage.
    stage_coefficients : list of (m, 3, 4) float64
        The coefficients ``T`` at the end of each stage (the global-to-local sequence of
        the paper's donkey-to-horse figure); kept in memory, not in ``to_dict``.
    evaluations : int
        Number of source-SDF evaluations.
    """

    energy: list = field(default_factory=list)
    step_rms: list = field(default_factory=list)
    modes: list = field(default_factory=list)
    stage_starts: list = field(default_factory=list)
    stage_ends: list = field(default_factory=list)
    stage_seconds: list = field(default_factory=list)
    stage_evaluations: list = field(default_factory=list)
    stage_coefficients: list = field(default_factory=list)
    evaluations: int = 0

    def to_dict(self) -> dict:
        return {
            "energy": [float(e) for e in self.energy],
            "step_rms": [float(s) for s in self.step_rms],
            "modes": [int(m) for m in self.modes],
            "stage_starts": [int(s) for s in self.stage_starts],
            "stage_ends": list(self.stage_ends),
            "stage_seconds": [float(t) for t in self.stage_seconds],
            "stage_evaluations": [int(k) for k in self.stage_evaluations],
            "evaluations": int(self.evaluations),
        }


@dataclass
class AdaptiveResult:
    """Output of :func:`optimize_adaptive`.

    Attributes
    ----------
    T : (m, 3, 4) float64
        Coefficients of the ``m`` modes reached.
    vertices : (n, 3) float64
        ``basis.deform(T)``.
    final : EnergyEvaluation
    history : OptimizationHistory
    status : {"converged", "stage_cap", "max_iterations", "rolled_back"}
        ``converged``: every stage ended by the stall test or a line search that found no
        decrease; ``stage_cap``: at least one stage was cut by its iteration cap
        (``max_iterations_per_stage``, or ``lm_iterations_per_stage``, which the fast path
        reaches by design); ``max_iterations``: the run was cut by ``max_iterations`` before
        ``m_max`` modes; ``rolled_back``: a NaN or infinite energy, gradient or direction
        stopped the run, which returns its last good state (the last accepted step; the
        rest pose when the very first evaluation was not finite).
    """

    T: np.ndarray
    vertices: np.ndarray
    final: EnergyEvaluation
    initial: EnergyEvaluation
    history: OptimizationHistory
    status: Status


def _finite(ev: EnergyEvaluation | None) -> bool:
    """Energy and gradient are free of NaN and infinity."""
    return ev is not None and bool(np.isfinite(ev.energy) and np.isfinite(ev.gradient).all())


def _evaluate_finite(energy: SDFEnergy, X: np.ndarray) -> EnergyEvaluation | None:
    """Evaluate at ``X``, or ``None`` when ``X`` or the result is not finite (never hand
    non-finite vertices to the SDF queries, never accept a non-finite value)."""
    if not np.isfinite(X).all():
        return None
    ev = energy.evaluate(X)
    return ev if _finite(ev) else None


def _precondition(grad: np.ndarray, basis: LBSBasis, kind: str) -> np.ndarray:
    """Search direction from the gradient blocks ``(m, 3, 4)``."""
    if kind == "none":
        return -grad
    if kind != "block":
        raise OptionError(f"preconditioner={kind!r}: expected one of {PRECONDITIONERS}")
    gram = basis.gram_blocks(grad.shape[0])
    # Tikhonov on each 4x4 block, relative to its trace, guards planar/degenerate supports.
    reg = 1e-9 * np.trace(gram, axis1=1, axis2=2)[:, None, None] * np.eye(4)
    # direction_j = -grad_j @ inv(gram_j): solve gram_j^T d_j^T = grad_j^T (gram_j symmetric)
    return -np.linalg.solve(gram + reg, grad.transpose(0, 2, 1)).transpose(0, 2, 1)


class _GradientStepper:
    """Algorithm 1's step: (preconditioned) gradient direction, Armijo backtracking."""

    def __init__(self, energy: SDFEnergy, basis: LBSBasis, options: RegistrationOptions):
        self.energy, self.basis, self.options = energy, basis, options
        self.alpha: float | None = None
        self.iterations_per_stage = options.max_iterations_per_stage
        self.stall_decrease = 0.0

    def start_stage(self, m: int) -> None:
        self.alpha = None

    def step(self, T: np.ndarray, current: EnergyEvaluation, X: np.ndarray) -> _Step:
        basis, options = self.basis, self.options
        n = basis.X0.shape[0]
        grad = basis.pullback(current.gradient, T.shape[0])  # B_m^T dE/dx
        direction = _precondition(grad, basis, options.preconditioner)
        slope = float(np.sum(grad * direction))
        if not np.isfinite(slope):
            return _Step(end="fault")
        if not slope < 0:
            return _Step(end="line_search")
        dir_rms = float(np.sqrt(np.sum(basis.displacement(direction) ** 2) / n))
        if dir_rms == 0:
            return _Step(end="stalled")
        cap = options.max_step / dir_rms  # step length that moves vertices by max_step RMS
        alpha = cap if self.alpha is None else min(self.alpha, cap)

        faults = []

        def trial(a: float):
            ev = _evaluate_finite(self.energy, basis.deform(T + a * direction))
            if ev is None:
                faults.append(a)
                return float("inf"), None
            return ev.energy, ev

        ls = armijo_backtracking(
            trial,
            current.energy,
            slope,
            alpha,
            c=options.armijo,
            shrink=options.backtrack,
            max_trials=options.max_backtracks,
        )
        if not ls.accepted:
            # a fault when even the shortest trial was not finite
            return _Step(end="fault" if faults and faults[-1] == ls.step else "line_search")
        # warm start: try a longer step next time if this one needed no backtracking
        self.alpha = ls.step / options.backtrack if ls.trials == 1 else ls.step
        return _Step(T=T + ls.step * direction, evaluation=ls.state, step_rms=ls.step * dir_rms)


class _LevenbergMarquardtStepper:
    """Our default step: Levenberg-Marquardt on the frozen-correspondence model
    (:mod:`.gauss_newton`), accepted on the true energy, damping by Nielsen's rule."""

    def __init__(self, energy: SDFEnergy, basis: LBSBasis, options: RegistrationOptions):
        self.energy, self.basis, self.options = energy, basis, options
        self.iterations_per_stage = options.lm_iterations_per_stage
        self.stall_decrease = options.lm_stall_decrease
        self.damping = options.lm_damping
        self.metric: np.ndarray | None = None
        self.nu = 2.0
        self.pattern = face_corner_pattern(energy.F, basis.X0.shape[0])  # sorted once per run

    def start_stage(self, m: int) -> None:
        # the last stage may have a cap of its own (one step per mode, the last until it stalls)
        last = m >= min(self.options.modes, self.basis.max_modes)
        final = self.options.lm_final_iterations
        self.iterations_per_stage = (final if last and final is not None
                                     else self.options.lm_iterations_per_stage)
        self.metric = subspace_metric(self.basis, m)
        # a new mode makes the model richer: relax the damping learned so far
        self.damping = max(self.damping / 3.0, self.options.lm_damping * 1e-3)
        self.nu = 2.0

    def step(self, T: np.ndarray, current: EnergyEvaluation, X: np.ndarray) -> _Step:
        """One step from the coefficients ``T (m, 3, 4)``, whose vertices are ``X (n, 3)``
        and whose evaluation is ``current``."""
        basis, options = self.basis, self.options
        m = T.shape[0]
        n = basis.X0.shape[0]
        # terms added to Eq. (3): the isometry prior's matrix in the vertices joins Eq. (3)'s
        # before the products with the skinning matrix; the landmarks' block is added after
        vertex_blocks = getattr(self.energy, "vertex_blocks", None)
        model = subspace_normal_equations(current, basis, m, self.energy.F, self.energy.weights,
                                          extra=vertex_blocks(X) if vertex_blocks is not None else None,
                                          pattern=self.pattern)
        extra = getattr(self.energy, "normal_matrix", None)
        A = extra(basis, m, X, folded=True) if extra is not None else None
        if A is not None:
            model = NormalEquations(A=model.A + A, g=model.g)
        for _ in range(options.max_backtracks):
            d = lm_solve(model, self.metric, self.damping)
            rms = float(np.sqrt(max(d @ self.metric @ d, 0.0) / n))  # >= 0 up to rounding
            if rms > options.lm_max_step:  # hard trust region on the vertex motion
                d *= options.lm_max_step / rms
                rms = options.lm_max_step
            if not np.all(np.isfinite(d)):
                return _Step(end="fault")
            if rms == 0:
                return _Step(end="stalled")
            predicted = model.predicted_decrease(d)
            if not predicted > 0:
                return _Step(end="line_search")
            trial_T = T + d.reshape(m, 3, 4)
            ev = _evaluate_finite(self.energy, basis.deform(trial_T))
            faulty = ev is None
            rho = -np.inf if faulty else (current.energy - ev.energy) / predicted
            if rho > options.armijo:
                self.damping *= damping_factor(rho)
                self.nu = 2.0
                return _Step(T=trial_T, evaluation=ev, step_rms=rms)
            self.damping *= self.nu
            self.nu *= 2.0
        # a fault when even the most damped (shortest) trial was not finite
        return _Step(end="fault" if faulty else "line_search")


@dataclass
class _Step:
    """One iteration's outcome: an accepted step, or why the stage ends."""

    T: np.ndarray | None = None
    evaluation: EnergyEvaluation | None = None
    step_rms: float = float("nan")
    end: StageEnd | None = None


_STEPPERS = {"paper": _GradientStepper, "lm": _LevenbergMarquardtStepper}


def optimize_adaptive(
    energy: SDFEnergy,
    basis: LBSBasis,
    options: RegistrationOptions,
    progress: Callable[[ProgressEvent], None] | None = None,
    start: np.ndarray | None = None,
) -> AdaptiveResult:
    """Run Algorithm 1 from the rest pose ``basis.X0`` (or from ``start``).

    Parameters
    ----------
    energy : SDFEnergy
        Eq. (3) for the source connectivity, quadrature points and target values.
    basis : LBSBasis
        Skinning subspace with at least ``options.modes`` modes.
    options : RegistrationOptions
        Optimizer, schedule, line search and preconditioner (see its docstring for units).
        ``optimizer="paper"`` takes Algorithm 1's gradient steps with a backtracking line
        search; ``optimizer="lm"`` takes Levenberg-Marquardt steps in the same subspaces and
        with the same mode schedule (:mod:`.gauss_newton`).
    progress : callable, optional
        Called with a :class:`ProgressEvent` after every accepted step.
    start : (k, 3, 4) float, optional
        Starting coefficients of the first ``k`` modes (zero: the rest pose). The
        initialization stage (:mod:`morphmodes_vol.initialize`) hands its global map over
        as mode 0's block; the schedule is unchanged (stage 1 optimizes mode 0 from there).

    Returns
    -------
    AdaptiveResult

    See Also
    --------
    AdaptiveRun : the same run one stage at a time (several starts in lockstep).
    """
    with single_threaded_blas():
        run = AdaptiveRun(energy, basis, options, progress, start)
        while not run.done:
            run.advance()
        return run.result()


class AdaptiveRun:
    """Algorithm 1 from one start, advanced one stage (one mode) at a time.

    :func:`optimize_adaptive` is ``AdaptiveRun(...)`` advanced until :attr:`done`;
    :meth:`morphmodes_vol.Registration.run` advances the starts in lockstep so that it can
    stop one early (``start_merge_distance``, ``start_strain_ratio``). Parameters as in
    :func:`optimize_adaptive`; the constructor evaluates the energy at the start.

    Attributes
    ----------
    T : (m, 3, 4) float64
        Coefficients after the last completed stage (or at the start).
    stage : int
        Modes active in the last completed stage (``initial_modes - 1`` before the first);
        the next stage adds mode ``stage + 1``.
    done : bool
        Every stage is completed, or the run was cut (``max_iterations``, a fault).
    """

    def __init__(
        self,
        energy: SDFEnergy,
        basis: LBSBasis,
        options: RegistrationOptions,
        progress: Callable[[ProgressEvent], None] | None = None,
        start: np.ndarray | None = None,
    ):
        self.t0 = time.perf_counter()
        self.energy, self.basis, self.options, self.progress = energy, basis, options, progress
        self.m_max = min(options.modes, basis.max_modes)
        self.history = OptimizationHistory()
        try:
            self.stepper = _STEPPERS[options.optimizer](energy, basis, options)
        except KeyError:
            raise OptionError(f"optimizer={options.optimizer!r}: expected one of {OPTIMIZERS}") from None

        m0 = min(options.initial_modes, self.m_max)  # 1 in Algorithm 1; m_max for a fixed subspace
        T = np.zeros((m0 - 1, 3, 4))
        if start is not None:
            start = np.asarray(start, dtype=np.float64)
            if start.ndim != 3 or start.shape[1:] != (3, 4):
                raise ValueError(f"start must have shape (k, 3, 4), got {start.shape}")
            k = min(start.shape[0], max(self.m_max, 1))
            T = np.zeros((max(m0 - 1, k), 3, 4))
            T[:k] = start[:k]
        self.T = T
        self.current = energy.evaluate(basis.deform(T))
        self.initial = self.current
        self.history.energy.append(self.current.energy)
        self.iteration = 0
        self.status: Status = "converged"
        self.stage = m0 - 1
        self.done = False
        if not _finite(self.current):
            log.warning("the energy at the rest pose is not finite: nothing to optimize")
            self.m_max, self.status, self.T = 0, "rolled_back", np.zeros((1, 3, 4))
        self._check_done()

    @property
    def vertices(self) -> np.ndarray:
        """``(n, 3)`` vertices at :attr:`T`."""
        return self.basis.deform(self.T)

    def _report(self, modes: int, stage_iteration: int, step_rms: float, eps: float) -> None:
        if self.progress is not None:
            self.progress(
                ProgressEvent(
                    modes=modes,
                    max_modes=self.m_max,
                    iteration=self.iteration,
                    stage_iteration=stage_iteration,
                    energy=self.current.energy,
                    step_rms=step_rms,
                    threshold=eps,
                    evaluations=self.energy.evaluations,
                    elapsed=time.perf_counter() - self.t0,
                )
            )

    def _check_done(self) -> None:
        if self.done:
            return
        if self.status in ("max_iterations", "rolled_back"):
            self.done = True
        elif self.stage >= self.m_max:
            self.done = True
            self.status = "stage_cap" if "iteration_cap" in self.history.stage_ends else "converged"
        elif self.iteration >= self.options.max_iterations:
            self.done, self.status = True, "max_iterations"

    def advance(self) -> None:
        """Run the next stage: add a mode, take steps until the stage ends."""
        if self.done:
            return
        energy, basis, options, stepper, history = (self.energy, self.basis, self.options,
                                                    self.stepper, self.history)
        T, current = self.T, self.current
        m = self.stage + 1
        stage_t0, stage_evals = time.perf_counter(), energy.evaluations
        if T.shape[0] < m:
            T = np.concatenate([T, np.zeros((1, 3, 4))])  # z <- [z; 0_12]
        eps = options.stall_threshold(self.stage)
        history.stage_starts.append(len(history.step_rms))
        stepper.start_stage(m)
        end: StageEnd = "iteration_cap"
        self.T, self.current = T, current
        self._report(m, 0, float("nan"), eps)
        for stage_iteration in range(1, stepper.iterations_per_stage + 1):
            if self.iteration >= options.max_iterations:
                end = "max_iterations"
                break
            out = stepper.step(T, current, basis.deform(T))
            if out.end is not None:
                end = out.end
                break
            previous = current.energy
            T, current = out.T, out.evaluation
            self.T, self.current = T, current
            self.iteration += 1
            history.energy.append(current.energy)
            history.step_rms.append(out.step_rms)
            history.modes.append(m)
            self._report(m, stage_iteration, out.step_rms, eps)
            small_decrease = stepper.stall_decrease > 0 and (
                previous - current.energy <= stepper.stall_decrease * previous)
            if out.step_rms < eps or small_decrease:
                end = "stalled"
                break
        self.T, self.current = T, current
        self.stage = m
        history.stage_ends.append(end)
        history.stage_coefficients.append(T.copy())
        history.stage_seconds.append(time.perf_counter() - stage_t0)
        history.stage_evaluations.append(energy.evaluations - stage_evals)
        log.info(
            "stage %d/%d ended (%s) after %d steps, energy %.6g, %d evaluations",
            m, self.m_max, end, len(history.step_rms) - history.stage_starts[-1],
            current.energy, energy.evaluations,
        )
        if end == "max_iterations":
            self.status = "max_iterations"
        elif end == "fault":  # T is still the last good (accepted) state
            log.warning("non-finite energy or gradient in stage %d: rolled back to the last "
                        "accepted step (energy %.6g)", m, current.energy)
            self.status = "rolled_back"
        self._check_done()

    def result(self) -> AdaptiveResult:
        """The run's outcome so far (complete once :attr:`done`)."""
        history = self.history
        history.evaluations = self.energy.evaluations
        return AdaptiveResult(
            T=self.T,
            vertices=self.basis.deform(self.T),
            final=self.current,
            initial=self.initial,
            history=history,
            status=self.status,
        )
