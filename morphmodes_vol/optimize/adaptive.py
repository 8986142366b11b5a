"""Algorithm 1: gradient descent in an adaptive skinning-eigenmode subspace.

Start with one mode (a global affine map); take gradient steps on the coefficients of the
active modes with a backtracking (Armijo) line search; when one step moves the vertices by
less than ``eps_stall`` (root-mean-square vertex motion, normalized units), add the next mode
(12 more coefficients, started at zero); stop after ``m_max`` modes.

Deviation from the paper (documented in docs/method.md): by default each mode's 3x4 block of
the gradient is multiplied by the inverse of its 4x4 Gram matrix ``[X0 1]^T diag(w_j)^2
[X0 1]``. Plain gradient descent on the raw coefficients is badly conditioned (translation
and linear parts of a block differ in scale by ~25x on the lion); ``preconditioner="none"``
gives the paper's plain step.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable, Literal

import numpy as np

from ..eigenbasis.lbs import LBSBasis
from ..energy import EnergyEvaluation, SDFEnergy
from ..errors import OptionError
from ..options import PRECONDITIONERS, RegistrationOptions
from .linesearch import armijo_backtracking

__all__ = ["optimize_adaptive", "OptimizationHistory", "ProgressEvent", "Status"]

log = logging.getLogger(__name__)

Status = Literal["converged", "stage_cap", "max_iterations"]
StageEnd = Literal["stalled", "line_search", "iteration_cap", "max_iterations"]


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
        ``max_iterations``.
    stage_seconds : list of float
        Wall time of each stage.
    stage_evaluations : list of int
        Source-SDF evaluations spent in each stage.
    stage_coefficients : list of (m, 3, 4) float64
        The coefficients ``T`` at the end of each stage (the global-to-local sequence of
        the paper's donkey-to-horse figure); kept in memory, not in ``to_dict``.
    evaluations : int
        Number of full source-SDF evaluations.
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
    status : {"converged", "stage_cap", "max_iterations"}
        ``converged``: every stage ended by the stall test or a line search that found no
        decrease; ``stage_cap``: at least one stage was cut by ``max_iterations_per_stage``;
        ``max_iterations``: the run was cut by ``max_iterations`` before ``m_max`` modes.
    """

    T: np.ndarray
    vertices: np.ndarray
    final: EnergyEvaluation
    initial: EnergyEvaluation
    history: OptimizationHistory
    status: Status


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


def optimize_adaptive(
    energy: SDFEnergy,
    basis: LBSBasis,
    options: RegistrationOptions,
    progress: Callable[[ProgressEvent], None] | None = None,
) -> AdaptiveResult:
    """Run Algorithm 1 from the rest pose ``basis.X0``.

    Parameters
    ----------
    energy : SDFEnergy
        Eq. (3) for the source connectivity, quadrature points and target values.
    basis : LBSBasis
        Skinning subspace with at least ``options.modes`` modes.
    options : RegistrationOptions
        Schedule, line search and preconditioner (see its docstring for units).
    progress : callable, optional
        Called with a :class:`ProgressEvent` after every accepted step.

    Returns
    -------
    AdaptiveResult
    """
    t0 = time.perf_counter()
    m_max = min(options.modes, basis.max_modes)
    history = OptimizationHistory()
    n = basis.X0.shape[0]

    current = energy.evaluate(basis.X0)
    initial = current
    history.energy.append(current.energy)
    m0 = min(options.initial_modes, m_max)  # 1 in Algorithm 1; m_max for a fixed subspace
    T = np.zeros((m0 - 1, 3, 4))
    iteration = 0
    status: Status = "converged"

    def report(modes: int, stage_iteration: int, step_rms: float, eps: float) -> None:
        if progress is not None:
            progress(
                ProgressEvent(
                    modes=modes,
                    max_modes=m_max,
                    iteration=iteration,
                    stage_iteration=stage_iteration,
                    energy=current.energy,
                    step_rms=step_rms,
                    threshold=eps,
                    evaluations=energy.evaluations,
                    elapsed=time.perf_counter() - t0,
                )
            )

    for stage in range(m0 - 1, m_max):
        if iteration >= options.max_iterations:
            status = "max_iterations"
            break
        m = stage + 1
        stage_t0, stage_evals = time.perf_counter(), energy.evaluations
        T = np.concatenate([T, np.zeros((1, 3, 4))])  # z <- [z; 0_12]
        eps = options.stall_threshold(stage)
        history.stage_starts.append(len(history.step_rms))
        alpha: float | None = None
        end: StageEnd = "iteration_cap"
        report(m, 0, float("nan"), eps)
        for stage_iteration in range(1, options.max_iterations_per_stage + 1):
            if iteration >= options.max_iterations:
                end = "max_iterations"
                break
            grad = basis.pullback(current.gradient, m)  # B_m^T dE/dx
            direction = _precondition(grad, basis, options.preconditioner)
            slope = float(np.sum(grad * direction))
            if not slope < 0:
                end = "line_search"
                break
            dir_rms = float(np.sqrt(np.sum(basis.displacement(direction) ** 2) / n))
            if dir_rms == 0:
                end = "stalled"
                break
            cap = options.max_step / dir_rms  # step length that moves vertices by max_step RMS
            alpha = cap if alpha is None else min(alpha, cap)

            def trial(a: float, T=T, direction=direction):
                ev = energy.evaluate(basis.deform(T + a * direction))
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
                end = "line_search"
                break
            T = T + ls.step * direction
            current = ls.state
            step_rms = ls.step * dir_rms  # ||delta x|| as RMS vertex motion
            iteration += 1
            history.energy.append(current.energy)
            history.step_rms.append(step_rms)
            history.modes.append(m)
            report(m, stage_iteration, step_rms, eps)
            if step_rms < eps:
                end = "stalled"
                break
            # warm start: try a longer step next time if this one needed no backtracking
            alpha = ls.step / options.backtrack if ls.trials == 1 else ls.step
        history.stage_ends.append(end)
        history.stage_coefficients.append(T.copy())
        history.stage_seconds.append(time.perf_counter() - stage_t0)
        history.stage_evaluations.append(energy.evaluations - stage_evals)
        log.info(
            "stage %d/%d ended (%s) after %d steps, energy %.6g, %d evaluations",
            m, m_max, end, len(history.step_rms) - history.stage_starts[-1],
            current.energy, energy.evaluations,
        )
        if end == "max_iterations":
            status = "max_iterations"
            break
    else:
        status = "stage_cap" if "iteration_cap" in history.stage_ends else "converged"

    history.evaluations = energy.evaluations
    return AdaptiveResult(
        T=T,
        vertices=basis.deform(T),
        final=current,
        initial=initial,
        history=history,
        status=status,
    )
