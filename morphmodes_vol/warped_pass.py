"""The warped pass (``warped_pass``): the warped rest field minimized from the starts and from
other orientations, its best results refined on Eq. (3), and hops through the field's
landscape (plain and with descriptor channels) from the best result of the runs and the
best of the refined ones.

docs/method.md, "The stages of a registration", has the method; :mod:`morphmodes_vol.warped_field`
the field itself.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.sparse.linalg import ArpackError

from .descriptors import heat_kernel_signature, surface_descriptor_grid
from .errors import MeshValidationError
from .runs import StartRun, ascending, rms
from .sdf import Grid
from .sdf.grid import trilinear_sample
from .warped_field import WarpedRestField, ZeroEnergy

if TYPE_CHECKING:
    from .register import Registration

__all__ = ["WARPED_PREFIX", "warped_pass", "warped_fields", "descriptor_channels", "descriptor_field"]

log = logging.getLogger(__name__)

WARPED_PREFIX = "warped: "
"""Put before a start's name for the run refined from the warped rest field."""
DESCRIPTOR_ERRORS = (MeshValidationError, ArpackError, np.linalg.LinAlgError)
"""Why a descriptor field may not be built (logged, and the descriptor hop skipped)."""


@dataclass(frozen=True)
class DescriptorChannels:
    """What :func:`descriptor_channels` makes: the source's heat kernel
    signatures ``source (n, c)``, the target's on the nodes of ``grid`` (``values``, as
    :func:`~morphmodes_vol.descriptors.surface_descriptor_grid` returns them) and the seconds
    spent."""

    source: np.ndarray
    values: np.ndarray
    grid: Grid
    seconds: float


@dataclass(frozen=True)
class WarpedFields:
    """What :func:`warped_fields` returns: the field, the candidates skipped,
    every field run to ``prune_modes`` modes (``first``), those stopped there (``pruned``,
    label -> field energy) and the finished runs (``results``); ``staged``: whether the runs
    were stopped at ``prune_modes`` at all; ``descriptors``: the descriptor field made beside
    them (:func:`descriptor_field`'s result or its error), else ``None``."""

    field: WarpedRestField
    skipped: list
    first: dict
    pruned: dict
    results: dict
    prune_modes: int
    staged: bool
    descriptors: tuple | Exception | None = None  # descriptor_field's result, or its error


def warped_fields(reg: "Registration", starts, candidates=(), descriptors=None) -> "WarpedFields":
    """The warped pass's field runs (``warped_pass``; :func:`warped_pass`): the field
    built once, minimized from every start and from ``candidates`` (``(label, T0)``;
    one that maps the source within ``start_merge_distance`` of a start already taken is
    skipped) to ``warped_prune_modes`` modes, then from those of field energy within
    ``warped_prune_ratio`` of the lowest to the end; with ``descriptors`` (the future of
    :func:`descriptor_channels_or_error`), also the descriptor field
    (:func:`descriptor_field`, or the error that stopped it). No source query after the
    field's one at the start, and nothing from the runs on Eq. (3): ``Registration.run`` lets it
    go on beside them (``overlap_field``)."""
    o = reg.options
    h = reg.quadrature.spacing
    field = WarpedRestField(reg.basis, reg.source_sdf_faces, reg.sample_target, h,
                            o.warped_band_cells * h,
                            terms=reg.with_terms(ZeroEnergy(reg.X0.shape[0])),
                            sign=o.source_sign, samples=o.occupancy_samples,
                            sample_weight=None if reg.confidence is None else reg.confidence.sample)
    field_starts = [(label, np.zeros((1, 3, 4)) if T0 is None else T0) for label, T0, _ in starts]
    skipped, placed = [], [reg.basis.deform(T) for _, T in field_starts]
    for label, T0 in candidates:  # other orientations; one that repeats a start is skipped
        X = reg.basis.deform(T0)
        if any(rms(X - P) < o.start_merge_distance for P in placed):
            skipped.append(label)
        else:
            field_starts.append((label, T0))
            placed.append(X)
    # every start to warped_prune_modes modes, then those of field energy within
    # warped_prune_ratio of the lowest to the end
    K = o.warped_prune_modes if 0 < o.warped_prune_modes < o.modes else o.modes
    staged = K < o.modes
    first = {label: field.minimize(T0, K, o.warped_iterations_per_stage) for label, T0 in field_starts}
    finite = [r.energy for r in first.values() if np.isfinite(r.energy)]
    pruned = {}
    if staged and finite:
        bar = o.warped_prune_ratio * min(finite)
        pruned = {label: r.energy for label, r in first.items() if not r.energy <= bar}
        if pruned:
            log.info("warped rest field: %d of %d starts stopped after %d modes (field energy "
                     "above %.3g)", len(pruned), len(first), K, bar)
    results = {}
    for label, begun in first.items():
        if label not in pruned:
            results[label] = begun if not staged else begun.then(field.minimize(
                begun.T, o.modes, o.warped_iterations_per_stage, first_mode=K + 1,
                start_damping=begun.damping))
    made = None
    if descriptors is not None:
        made = descriptors.result()  # an error is raised again where the field is used
        if not isinstance(made, Exception):
            made = descriptor_field(reg, field, made)
    return WarpedFields(field, skipped, first, pruned, results, K, staged, made)


def warped_pass(reg: "Registration", starts, forward: "StartRun", progress, candidates=(),
                fields: "WarpedFields | None" = None):
    """``warped_pass`` (docs/method.md, "The stages of a registration"): minimize the warped rest
    field (:class:`~morphmodes_vol.warped_field.WarpedRestField`) from every start (and from
    ``candidates``, ``(label, T0)`` pairs: the initialization stage's other orientations with
    ``warped_candidates``; past ``warped_prune_modes`` modes only from those of field energy
    within ``warped_prune_ratio`` of the lowest), rank the field results by the objective
    after a refinement on the coarse grid (:func:`_rank`; ``ranking`` in the report),
    refine the first on Eq. (3) on the grid (one stage with all modes), and compare it with
    the ``forward`` run's result by the objective on the full grid (``objectives`` and
    ``kept_before_hops`` in the report); then hop (:func:`_hops`) from the runs' result
    and from the refined one, and keep the lowest objective after the hops (decision
    0013). Returns the field, the refining runs, the report (``metrics["warped_pass"]``;
    each hop's ``chain``: the result its chain started from) and the seconds spent on the
    field (building it and minimizing it). ``fields``: the field runs made beside Algorithm 1's
    (:func:`warped_fields`, ``overlap_field``), else made here."""
    o = reg.options
    if fields is None:
        fields = warped_fields(reg, starts, candidates)
    field, first, pruned, results = fields.field, fields.first, fields.pruned, fields.results
    for label, run in results.items():
        log.info("warped rest field from the %s start: %d evaluations, %d steps, %.2f s, "
                 "field energy %.4g", label, run.evaluations, run.steps, run.seconds, run.energy)
    energies = {label: r.energy for label, r in results.items()}
    options = o.replace(initial_modes=o.modes, lm_final_iterations=o.warped_polish_iterations)
    ranking, ranked = _rank(reg, results, options, progress)
    chosen = ascending(ranking)[0]
    runs = list(ranked.values())
    # the refined result is judged by the objective on the full grid when something is
    # compared with it: the runs' result, a hop (the hops below run as planned here,
    # unless the objective is not finite or the descriptors fail)
    descriptor_hop = o.warped_descriptors and reg.Y is not None  # an SDF target has no surface
    judge = forward is not None or o.warped_hops > 0 or descriptor_hop
    refined = ranked.get(chosen)
    if refined is None or refined.coarse:  # ranked on the grid: refined there already
        refined = reg.runner.run([(WARPED_PREFIX + chosen, results[chosen].T, options)], progress, judge=judge)[0]
        runs.append(refined)
    ran = {} if forward is None else {forward.label: reg.runner.full_grid_objective(forward)}  # field_only: no runs
    compared = {**ran, refined.label: refined.energy}
    # the lowest objective, the runs' result first among ties, a NaN one last; a candidate
    # that repeats a start's placement (a symmetry of the shape) never reached the field
    # (InitialAlignment.candidate_indices), so a tie across a symmetry cannot turn the result
    kept = ascending(compared)[0]
    log.info("warped rest field: objective %s: kept the %s result",
             ", ".join(f"{k} {e:.4g}" for k, e in compared.items()), kept)
    # the hops start from the runs' result and from the refined field result, the lower
    # first; the lowest objective after them is kept: a near-tie of the two does not decide
    # where the hops explore (decision 0013)
    of = {refined.label: refined} | ({} if forward is None else {forward.label: forward})
    heads = ascending({k: compared[k] for k in ascending(ran)[:1] + [refined.label]})
    kinds, descriptors, descriptor_seconds = _hop_fields(
        reg, fields, descriptor_hop and np.isfinite(compared[kept]))
    ends, hops, hop_fields = {}, [], []
    for head in heads:
        current, objective = _hops(reg, kinds, of[head], compared[head], options, progress, runs,
                                   hops, hop_fields, "" if head == heads[0] else f" from {head}")
        ends[current.label] = (objective, current)
    current = ends[ascending({k: e for k, (e, _) in ends.items()})[0]][1]
    report = {"kept": current.label, "kept_before_hops": kept, "objectives": compared,
              "field_energies": energies, "ranking": ranking, "refined_start": chosen,
              "skipped_candidates": fields.skipped,
              "pruned": pruned, "prune_modes": fields.prune_modes if fields.staged else None,
              "field_energies_at_prune": {label: r.energy for label, r in first.items()} if fields.staged else {},
              "field_nodes": int(len(field.points)), "hops": hops, "descriptors": descriptors}
    spent = [*results.values(), *(first[label] for label in pruned), *hop_fields]  # every field run, whole
    report["field_evaluations"] = int(sum(r.evaluations for r in spent))
    seconds = float(field.build_seconds + sum(r.seconds for r in spent) + descriptor_seconds)
    return field, runs, report, seconds


def _rank(reg: "Registration", results: dict, options, progress) -> tuple[dict, dict]:
    """The field results (label -> :class:`~morphmodes_vol.warped_field.WarpedRun`) ranked
    by the objective on the full grid after a refinement on Eq. (3) (``options``: one
    stage with all modes), when there are several: the objective, not a near-tie of field
    energies, chooses the one refined on the grid (decision 0014). The refinements run on
    the coarse pass's grid (every other node) when it has nodes enough
    (:meth:`~morphmodes_vol.runs.StartRunner.coarse_grid_fits`), else on the grid. Returns
    label -> objective (a lone result: its field energy) and label -> refining run."""
    if len(results) < 2:
        return {label: r.energy for label, r in results.items()}, {}
    run = reg.runner.run_coarse if reg.runner.coarse_grid_fits() else reg.runner.run
    # one at a time: none is stopped for another (runs in lockstep would be, StartRunner.run)
    ranked = {label: run([(WARPED_PREFIX + label, r.T, options)], progress)[0] for label, r in results.items()}
    return {label: r.energy for label, r in ranked.items()}, ranked


def _hop_fields(reg: "Registration", fields: "WarpedFields", descriptor_hop: bool):
    """The fields the hops go through: ``("hop", field, warped_hops)`` and, with
    ``descriptor_hop``, ``("descriptor hop", field with descriptor channels, 1)`` when the
    channels can be made (``(name, field, count)``). Returns them, the descriptors' report
    and the seconds spent on the descriptor field."""
    o = reg.options
    kinds, descriptors, seconds = [("hop", fields.field, o.warped_hops)], {}, 0.0
    if o.warped_descriptors and reg.Y is None:
        log.info("warped_descriptors: a target given as an SDF has no surface for descriptors")
        descriptors = {"skipped": "the target is an SDF, not a mesh"}
    elif descriptor_hop:
        # docs/method.md, "The stages of a registration"
        try:
            made = fields.descriptors
            if isinstance(made, Exception):
                raise made
            dfield, grid_nodes, seconds = made or descriptor_field(reg, fields.field)
        except DESCRIPTOR_ERRORS as exc:
            log.warning("warped_descriptors: no heat kernel signature (%s); no descriptor hop", exc)
            descriptors = {"skipped": f"no heat kernel signature: {exc}"}
        else:
            descriptors = {"channels": int(dfield.d0.shape[1]), "grid_nodes": grid_nodes}
            kinds.append(("descriptor hop", dfield, 1))
    return kinds, descriptors, seconds


def _hops(reg: "Registration", kinds, current: "StartRun", objective: float, options, progress,
          runs: list, hops: list, hop_fields: list, suffix: str = ""):
    """Hops through the field's landscape from the result ``current`` of objective
    ``objective`` (``warped_hops``): the field's minimum near it with all modes, refined on
    Eq. (3), kept when its objective is below the kept one's, the next hop from there; then,
    with ``warped_descriptors``, one hop through the field with the heat kernel signatures as
    channels (``kinds``, :func:`_hop_fields`). The hops' runs (labelled with ``suffix``) are
    appended to ``runs``, their reports (``chain``: the label of the result they started
    from) to ``hops``, their field runs to ``hop_fields``. Returns the result kept and its
    objective."""
    o = reg.options
    chain = current.label
    for name, hop_field, count in kinds:
        for i in range(count if np.isfinite(objective) else 0):
            moved = hop_field.minimize(current.result.T, o.modes, o.warped_hop_iterations, first_mode=o.modes)
            hop_fields.append(moved)
            run = reg.runner.run([(f"{WARPED_PREFIX}{name} {i + 1}{suffix}", moved.T, options)], progress)[0]
            runs.append(run)
            accepted = bool(run.energy < objective)  # no margin (decision 0011)
            hops.append({"start": run.label, "from": current.label, "chain": chain,
                         "field_energy": float(moved.energy), "objective": float(run.energy),
                         "accepted": accepted, "field": "descriptors" if hop_field.d0 is not None else "plain"})
            log.info("%s from the %s result: field energy %.4g, objective %.4g against %.4g: %s", run.label,
                     current.label, moved.energy, run.energy, objective, "kept" if accepted else "not kept")
            if not accepted:
                break
            current, objective = run, run.energy
    return current, objective


def descriptor_channels(reg: "Registration") -> "DescriptorChannels":
    """The descriptor channels of the warped field (``warped_descriptors``; docs/method.md,
    "Descriptors in the warped field"): the heat kernel signatures of the source and the
    target mesh, the target's on a grid of half the quadrature's nodes over its box. They
    depend on the two meshes alone: ``Registration.run`` makes them beside the initialization
    (``overlap_field``)."""
    o = reg.options
    t = time.perf_counter()
    source = heat_kernel_signature(reg.X0, reg.source_sdf_faces, seed=o.seed)
    target = heat_kernel_signature(reg.Y, reg.target_sdf_faces, seed=o.seed)
    grid = Grid.covering(reg.quadrature.origin, reg.quadrature.upper, max(max(reg.quadrature.shape) // 2, 2))
    values = surface_descriptor_grid(reg.Y, reg.target_sdf_faces, target, grid)
    return DescriptorChannels(source, values, grid, time.perf_counter() - t)


def descriptor_channels_or_error(reg: "Registration") -> "DescriptorChannels | Exception":
    """:func:`descriptor_channels`, or the error that stopped it (raised again where
    the descriptor hop is made, which logs it and goes without)."""
    try:
        return descriptor_channels(reg)
    except DESCRIPTOR_ERRORS as exc:
        return exc


def descriptor_field(reg: "Registration", field: WarpedRestField,
                      channels: "DescriptorChannels | None" = None) -> tuple[WarpedRestField, int, float]:
    """``field`` with the descriptor channels (``channels``, made by
    :func:`descriptor_channels` when not given). Returns the field, the node count of
    the target's descriptor grid and the seconds spent on both."""
    c = descriptor_channels(reg) if channels is None else channels
    t = time.perf_counter()
    dfield = field.with_descriptors((c.source, lambda P: trilinear_sample(c.values, c.grid, P)),
                                    reg.options.warped_descriptor_weight)
    seconds = c.seconds + time.perf_counter() - t
    log.info("descriptor field: heat kernel signatures and the target's grid of %d nodes (%.2f s)",
             c.grid.size, seconds)
    return dfield, int(c.grid.size), seconds
