"""What a registration reports: the stages' outcome, the correspondence onto the target, the
metrics of the result and what it cost (``RegistrationResult.metrics``)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from .landmarks import landmark_rms
from .mesh import bbox_diagonal
from .runs import StartRun
from .sdf import closest_points

if TYPE_CHECKING:
    from .register import Registration, RegistrationResult

__all__ = ["Outcome", "correspondence", "result_metrics", "cost_metrics", "landmark_metrics"]

log = logging.getLogger(__name__)


@dataclass
class Outcome:
    """What the stages of :meth:`Registration.run` leave: the kept run (``chosen``), every
    run, the initialization's report, the warped pass's field and report, the reverse
    registration and two-way's report, and the residual at the start."""

    chosen: StartRun | None
    runs: list
    init_summary: dict
    warped_field: object = None
    warped: dict = field(default_factory=dict)
    reverse: "RegistrationResult | None" = None
    two_way: dict = field(default_factory=dict)
    initial: object = None
    rest_evaluator: object = None

    def keep(self, runs: list, kept: str) -> None:
        """Add a stage's ``runs``; the one labelled ``kept``, if among them, is chosen."""
        self.runs += runs
        self.chosen = next((r for r in runs if r.label == kept), self.chosen)


def correspondence(reg: "Registration", X: np.ndarray, vertices: np.ndarray):
    """The registered vertices' closest target points (faces ``(n,)`` and barycentrics
    ``(n, 3)``, ``None`` for an SDF target), their distances ``(n,)`` and the diagonal they
    are measured against; ``X``: the vertices in the normalized frame, ``vertices`` in the
    source's."""
    if reg.Y is not None:
        # in the normalized frame (Open3D searches in float32); barycentrics and face ids
        # are invariant under the similarity, distances scale by 1 / normalization.scale
        cp = closest_points(reg.Y, reg.target_faces, X)
        return cp.faces, cp.barycentrics, cp.distance, bbox_diagonal(reg.Y)
    # no target faces: the distance is |target SDF| at the registered vertices, over
    # the diagonal of the zero level set's box (both in the target's frame)
    dist = np.abs(reg.target_sdf.sample(vertices))
    return None, None, dist, float(np.linalg.norm(np.subtract(*reg.target_sdf.surface_bounds())))


def result_metrics(reg: "Registration", o: "Outcome", out, dist: np.ndarray, diag: float) -> dict:
    """The result's energies and residuals, the stages' reports and every run's record."""
    initial, chosen = o.initial, o.chosen
    metrics = {
        # at the rest pose when a run started there (the aligned start's is better
        # already); with field_only at the rest pose
        "initial_energy": float(initial.energy),
        "final_energy": float(out.final.energy),
        "initial_sdf_rms": initial.rms_residual,
        "final_sdf_rms": out.final.rms_residual,
        "sdf_rms_units": "fraction of the union bounding-box diagonal",
        "mean_distance_to_target": float(dist.mean() / diag),
        "target_sdf_bytes": int(reg.target_sdf.nbytes),
    }
    if metrics["final_sdf_rms"] > 0.5 * metrics["initial_sdf_rms"]:
        log.warning(
            "the SDF residual fell only from %.3g to %.3g: the registration may have "
            "failed (source and target far apart or very differently oriented?)",
            metrics["initial_sdf_rms"], metrics["final_sdf_rms"],
        )
    metrics.update(o.init_summary)
    if o.warped:
        metrics["warped_pass"] = o.warped
    if o.two_way:
        metrics["two_way"] = o.two_way
    metrics["edge_strain"] = chosen.strain
    metrics["start"] = chosen.label
    metrics["starts"] = [{"start": r.label, "energy": r.energy, "energy_grid": r.energy_grid,
                          "energy_after_modes": r.judged if r.energy_grid else None,
                          "edge_strain": r.strain,
                          "evaluations": r.result.history.evaluations,
                          "stopped_after_modes": r.stopped, "stop_reason": r.reason}
                         for r in o.runs]
    return metrics


def cost_metrics(reg: "Registration", o: "Outcome", compared) -> dict:
    """What the registration cost, in source-SDF evaluations and points queried
    (``compared``: the comparisons' evaluations, points and seconds)."""
    runs, m = o.runs, {}
    # with two_way, the counts below include the reverse registration's (it queries the
    # target mesh, on a grid of the same box)
    rm = {} if o.reverse is None else o.reverse.metrics
    m["evaluations_all_starts"] = (sum(r.result.history.evaluations for r in runs)
                                   + rm.get("evaluations_all_starts", 0))
    # of which on the coarse pass's grid (coarse_starts), each a few times cheaper
    m["coarse_evaluations_all_starts"] = (sum(r.result.history.evaluations for r in runs
                                              if r.coarse)
                                          + rm.get("coarse_evaluations_all_starts", 0))
    # the objectives that compared runs (every node of the fine or the coarse grid),
    # not counted above
    m["comparison_evaluations"] = int(compared[0]) + rm.get("comparison_evaluations", 0)
    # every point sent to the source mesh's closest-point queries: the runs' evaluations,
    # the comparisons, the initial alignment's source field; over the
    # grid's nodes, the cost in evaluations of Eq. (3) on the full grid (the paper's)
    queried = (sum(r.points_queried for r in runs) + int(compared[1])
               + int(o.init_summary.get("init_field_nodes", 0)) + rm.get("points_queried", 0)
               + (o.warped_field.nodes_queried if o.warped_field is not None else 0)
               + (o.rest_evaluator.points_queried if o.rest_evaluator is not None else 0))
    m["points_queried"] = queried
    m["full_grid_equivalents"] = queried / reg.Q.shape[0]
    return m


def landmark_metrics(reg: "Registration", vertices: np.ndarray, target_diagonal: float) -> dict:
    """RMS landmark distance of the rest pose and of the registered ``vertices (n, 3)``,
    in the target's units and as a fraction of its bounding-box diagonal."""
    before = landmark_rms(reg.source_vertices, reg.landmarks)
    after = landmark_rms(vertices, reg.landmarks)
    return {"landmarks": len(reg.landmarks), "initial_landmark_rms": before,
            "landmark_rms": after, "landmark_rms_fraction": after / target_diagonal}
