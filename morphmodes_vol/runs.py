"""Algorithm 1 from several starts at once, and the rules that stop, compare and keep runs.

:class:`StartRunner` advances the runs of one registration in lockstep, a mode at a time,
and stops those another makes redundant; :func:`select_start` is the rule that keeps one
run among finished ones.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Callable

import numpy as np

from .blas import single_threaded_blas
from .metrics import edge_strain
from .optimize import AdaptiveRun, ProgressEvent

if TYPE_CHECKING:
    from .register import Registration

__all__ = ["StartRun", "StartRunner", "select_start", "ascending", "rms"]

log = logging.getLogger(__name__)

COARSE_SUFFIX = " (coarse)"
"""Added to a start's name for its run in the coarse pass (``coarse_starts``)."""
MIN_COARSE_NODES = 24
"""Fewest nodes along the longest side of the coarse pass's grid (``coarse_starts``), so
grids under 48 nodes run one pass."""


@dataclass
class StartRun:
    """Algorithm 1 from one start: its result, SDF-query time, full-grid objective, edge
    strain; while it runs, its :class:`AdaptiveRun` and evaluator; ``stopped``: the modes after
    which it was stopped early (``reason``: ``merged``, ``outstretched`` or ``not chosen``), else
    ``None``."""

    label: str
    result: object
    sdf_seconds: float
    energy: float
    strain: float
    run: AdaptiveRun | None = None
    energy_term: object = None
    stopped: int | None = None
    reason: str | None = None
    judged: int | None = None  # the stage at which ``energy`` was computed while running
    seen: int | None = None  # the stage of ``vertices`` and ``strain`` while running
    vertices: np.ndarray | None = None
    objective: Callable[[np.ndarray], float] | None = None  # judged by while running (None: fine grid)
    points_queried: int = 0  # points its evaluator sent to the closest-point queries
    energy_grid: str | None = None  # where ``energy`` was computed: "fine", "coarse" (None: never)
    coarse: bool = False  # run on the coarse pass's grid (every other node)


def select_start(runs: list[StartRun], factor: float) -> StartRun:
    """The least distorted run (lowest edge strain) among those whose objective is within
    ``factor`` of the lowest: the same body in another pose is close to an isometry, and a
    registration with wrong correspondences may fit the SDF as well but stretch the surface
    more (docs/method.md)."""
    finite = [r for r in runs if np.isfinite(r.energy)]
    if not finite:
        return runs[0]
    lowest = min(r.energy for r in finite)
    return min((r for r in finite if r.energy <= factor * lowest), key=lambda r: r.strain)


def ascending(values: dict) -> list:
    """The keys of ``values`` by ascending value, NaN and infinite values last, ties in
    their order."""
    return sorted(values, key=lambda k: (not np.isfinite(values[k]), np.nan_to_num(values[k], nan=0.0)))


def rms(D: np.ndarray) -> float:
    """RMS length of the rows of ``D (n, 3)``: the RMS distance between two placements of
    the vertices."""
    return float(np.sqrt(np.mean(np.sum(D**2, axis=1))))


def comparison_counters(evaluators) -> tuple[int, int, float]:
    """Evaluations, points queried and seconds of the comparison objectives' evaluators
    (:meth:`Registration._cached`), summed; ``run`` reports the difference it made."""
    evaluators = list(evaluators)
    return (sum(e.evaluations for e in evaluators), sum(e.points_queried for e in evaluators),
            sum(e.seconds for e in evaluators))


def labelled(progress: Callable[[ProgressEvent], None], label: str) -> Callable[[ProgressEvent], None]:
    """``progress`` with the events' ``start`` set to ``label``."""
    return lambda event: progress(replace(event, start=label))


class StartRunner:
    """Runs Algorithm 1 for a :class:`~morphmodes_vol.register.Registration`: from its
    starts in lockstep (:meth:`run`), stopping redundant runs (:meth:`redundant`,
    :meth:`choose_now`) and judging finished ones by the registration's objective."""

    def __init__(self, reg: "Registration"):
        self.reg = reg

    def run(self, starts, progress, energy=None, objective=None, judge: bool = True) -> list["StartRun"]:
        """Algorithm 1 from every start, advanced in lockstep one stage (mode) at a time.

        After each stage from ``start_check_modes`` on, a run stops early when another
        makes it redundant (docs/method.md, "The stages of a registration"),
        pair by pair:

        - *merged*: the two runs' vertices are closer than ``start_merge_distance`` (RMS,
          normalized units) to each other; the one that stretches the edges more stops;
        - *outstretched*: a run's edge strain is more than ``start_strain_ratio`` times the
          other's, and the other's objective (``objective``) is within ``select_energy_factor``
          of its own: the final selection (:func:`select_start`) would not keep it.

        After ``start_choice_modes`` modes, the final selection is made among the runs
        still going, and the others stop (*not chosen*). ``energy``: the evaluator factory
        (default :meth:`Registration.energy`); ``objective``: what the runs are compared by while they
        run (default :meth:`Registration.objective`, Eq. 3 on the full grid; the coarse pass gives
        :meth:`Registration.coarse_objective`, and the report names the grid accordingly). A run that
        ends is judged by :meth:`Registration.objective` whatever ``objective`` is; ``judge=False`` (a
        lone run that nothing is chosen against) keeps its own final energy instead, on its
        quadrature, and saves that evaluation.
        """
        o = self.reg.options
        live = []
        for label, start, options in starts:
            if len(starts) > 1:
                log.info("Algorithm 1 from start %s", label)
            evaluator = (energy or self.reg.energy)()
            shown = progress if progress is None else labelled(progress, label)
            live.append(StartRun(label, None, 0.0, float("nan"), float("nan"), energy_term=evaluator,
                                 objective=objective,
                                 run=AdaptiveRun(evaluator, self.reg.basis, options, shown, start)))
        runs = list(live)
        with single_threaded_blas():
            while live:
                for r in live:
                    r.run.advance()
                going = [r for r in live if not r.run.done]
                stage = going[0].run.stage if going else 0
                if len(going) > 1 and stage >= o.start_check_modes:
                    for a, b in [(a, b) for i, a in enumerate(going) for b in going[i + 1:]]:
                        if a.stopped is None and b.stopped is None:
                            self.redundant(a, b)
                    going = [r for r in going if r.stopped is None]
                if len(going) > 1 and o.start_choice_modes is not None and stage >= o.start_choice_modes:
                    self.choose_now(going)
                for r in [r for r in live if r.run.done or r.stopped is not None]:
                    self._finish(r, judge)
                    live.remove(r)
        return runs

    def _finish(self, r: "StartRun", judge: bool = True) -> None:
        """Keep a run's result, SDF time, edge strain and (when it ran to the end) objective
        (``judge=False``: its final energy on its own quadrature); let its evaluator go."""
        self._state_of(r)  # the strain at the run's last state
        r.result = r.run.result()
        r.sdf_seconds = r.energy_term.seconds
        r.points_queried = r.energy_term.points_queried
        if r.stopped is None and not judge:
            r.energy, r.judged = float(r.result.final.energy), r.run.stage
            r.energy_grid = "fine" if self.reg.runs_on_full_grid() and r.objective is None else "own"
        elif r.stopped is None:  # a stopped run keeps the objective it was judged by (or NaN)
            r.energy = self._comparable_energy(r)
            r.judged, r.energy_grid = r.run.stage, "fine"
        r.run = r.energy_term = r.vertices = r.objective = None

    def _state_of(self, r: "StartRun") -> np.ndarray:
        """A running start's vertices ``(n, 3)`` now, its edge strain left in ``r.strain``;
        computed once per stage, however many pairs and choices ask."""
        if r.seen != r.run.stage:
            r.seen, r.vertices = r.run.stage, r.run.vertices
            r.strain = edge_strain(self.reg.X0, r.vertices, self.reg.source_faces)
        return r.vertices

    def _objective_of(self, r: "StartRun") -> float:
        """The objective (``r.objective``, else :meth:`Registration.objective`) of a running start's
        current state, computed once per stage."""
        if r.judged != r.run.stage:
            r.judged, r.energy = r.run.stage, (r.objective or self.reg.objective)(self._state_of(r))
            r.energy_grid = "fine" if r.objective is None else "coarse"
        return r.energy

    def full_grid_objective(self, r: "StartRun") -> float:
        """A finished run's objective on the full grid: its energy when it was judged there,
        else :meth:`Registration.objective` of its result."""
        return r.energy if r.energy_grid == "fine" else self.reg.objective(r.result.vertices)

    def redundant(self, a: "StartRun", b: "StartRun") -> "StartRun | None":
        """The run of ``a``, ``b`` (at the same stage) that need not go on, or ``None``;
        marks it stopped."""
        o = self.reg.options
        Xa, Xb = self._state_of(a), self._state_of(b)
        sa, sb = a.strain, b.strain
        stage = a.run.stage
        distance = rms(Xa - Xb)
        if distance < o.start_merge_distance:
            loser, reason = (a, "merged") if sa > sb else (b, "merged")
        else:
            hi, lo = (a, b) if sa > sb else (b, a)
            ratio = o.start_strain_ratio
            if np.isinf(ratio) or not max(sa, sb) > ratio * min(sa, sb):
                return None
            # the objectives are compared only when the strains call for it (two evaluations
            # on a full grid); the less stretched run must fit within select_energy_factor
            e_hi, e_lo = self._objective_of(hi), self._objective_of(lo)
            if not (np.isfinite(e_lo) and e_lo <= o.select_energy_factor * e_hi):
                return None
            loser, reason = hi, "outstretched"
        loser.stopped, loser.reason = stage, reason
        log.info("after %d modes the start from the %s stops (%s: RMS distance %.3g, edge "
                 "strain %s %.3f, %s %.3f)", stage, loser.label, reason, distance,
                 a.label, sa, b.label, sb)
        return loser

    def choose_now(self, runs: list["StartRun"]) -> "StartRun":
        """The final selection (:func:`select_start`) among ``runs`` (at the same stage),
        made now: the others are marked stopped (*not chosen*); returns the kept run."""
        for r in runs:
            self._objective_of(r)  # and the strain, by _state_of
        kept = select_start(runs, self.reg.options.select_energy_factor)
        for r in runs:
            if r is not kept:
                r.stopped, r.reason = r.run.stage, "not chosen"
        log.info("after %d modes the start from the %s is kept (edge strain %s; objective %s)",
                 kept.run.stage, kept.label, ", ".join(f"{r.label} {r.strain:.3f}" for r in runs),
                 ", ".join(f"{r.label} {r.energy:.3g}" for r in runs))
        return kept

    def _comparable_energy(self, r: "StartRun") -> float:
        """The objective of a finished run's result (Eq. 3 plus the isometry prior and
        landmarks when on) with Eq. (3) on the full grid: its own final energy when it ran
        there, else evaluated (a band quadrature differs per run; the coarse pass runs on
        every other node)."""
        if self.reg.runs_on_full_grid() and r.objective is None:
            return float(r.result.final.energy)
        return self.reg.objective(r.result.vertices)

    def coarse_grid_fits(self) -> bool:
        """Every other node of the quadrature grid makes a grid of at least
        ``MIN_COARSE_NODES`` along its longest side (the coarse pass's and the warped
        pass's ranking's grid)."""
        return max(self.reg.quadrature.shape) >= 2 * MIN_COARSE_NODES

    def run_coarse(self, starts, progress) -> list["StartRun"]:
        """:meth:`run` on the coarse grid (every other node of the quadrature grid: Eq. (3) by
        :meth:`Registration.coarse_energy`, compared by :meth:`Registration.coarse_objective`),
        each run named with ``COARSE_SUFFIX`` and marked ``coarse``; a run that ends is judged
        on the full grid, as by :meth:`run`."""
        runs = self.run([(label + COARSE_SUFFIX, start, options) for label, start, options in starts],
                        progress, self.reg.coarse_energy, self.reg.coarse_objective)
        for r in runs:
            r.coarse = True
        return runs

    def passes(self, starts, progress) -> tuple["StartRun", list["StartRun"]]:
        """Algorithm 1 from the starts: with ``coarse_starts``, every start on the coarse grid
        (every other node), else on the grid. Returns the run chosen and every run."""
        factor = self.reg.options.select_energy_factor
        coarse_pass = self.reg.options.coarse_starts and self.coarse_grid_fits()
        if self.reg.options.coarse_starts and not coarse_pass:
            log.info("grid of %d nodes: too coarse for a coarse pass (coarse_starts)", max(self.reg.quadrature.shape))
        if coarse_pass:
            # every start on the coarse grid; the grid itself is the warped pass's, whose
            # refinements run on it (docs/decisions/0004)
            runs = self.run_coarse(starts, progress)
            chosen = select_start([r for r in runs if r.stopped is None], factor)
        else:
            # a lone run is not compared with anything (unless two_way compares it with the
            # run from the reverse registration): no objective on the full grid
            runs = self.run(starts, progress, judge=len(starts) > 1 or self.reg.options.two_way
                                    or self.reg.options.warped_pass)
            chosen = select_start([r for r in runs if r.stopped is None], factor)
        return chosen, runs
