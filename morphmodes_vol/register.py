"""The registration pipeline: preprocessing -> eigenbasis -> optimize -> export-ready result.

:class:`Registration` holds the expensive state of one source/target pair (normalized
meshes, quadrature, target SDF, eigenbasis), built once; :func:`register` is the one-call
function.
"""

from __future__ import annotations

import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .blas import single_threaded_blas
from .eigenbasis import LBSBasis, mesh_skinning_weights, to_paper_z
from .energy import SDFEnergy
from .errors import OptionError
from .initialize import InitialAlignment, align
from .isometry import IsometryEnergy
from .landmarks import LandmarkEnergy, Landmarks, as_landmarks
from .limits import check_memory, estimate_memory
from .mesh import MeshLike, Normalization, as_mesh, joint_normalization
from .metrics import ground_truth_error, shape_metrics
from .optimize import OptimizationHistory, ProgressEvent
from .options import RegistrationOptions
from .quadrature import band_quadrature, every_other_node
from .repair import sdf_faces
from .report import Outcome, correspondence, cost_metrics, landmark_metrics, result_metrics
from .runs import StartRunner, comparison_counters
from .sdf import Grid, build_target_sdf
from .sdf.confidence import target_confidence
from .sdf.source import is_closed, resolve_sign
from .stages import SourceEigenbasis, TargetField
from .targets import as_target_sdf, save_target_sdf, scan_target
from .two_way import two_way_pass
from .warped_pass import descriptor_channels_or_error, warped_fields, warped_pass

__all__ = ["register", "Registration", "RegistrationResult", "ground_truth_error", "scan_target"]

log = logging.getLogger(__name__)


def _label(mesh, default: str) -> str:
    """A file name for messages, or ``default`` for in-memory meshes."""
    return str(mesh) if isinstance(mesh, (str, os.PathLike)) else default


@dataclass
class RegistrationResult:
    """Everything a registration produced.

    Attributes
    ----------
    vertices : (n, 3) float64
        Registered source vertices in the source's original frame (same order as the input).
    faces : (f, 3) int64
        Source faces, unchanged.
    T : (m, 3, 4) float64
        Affine block of each active mode, in the normalized frame (Eq. 6).
    z : (12 m,) float64
        The same coefficients in the paper's order (Eq. 5-6).
    weights : (n, m_max) float64
        Skinning weights (skinning eigenmodes, Eq. 4), ``W^T M W = I``.
    eigenvalues : (m_max,) float64
    history : OptimizationHistory
    status : str
        ``converged``, ``stage_cap``, ``max_iterations`` or ``rolled_back`` (see
        :class:`~morphmodes_vol.optimize.adaptive.AdaptiveResult`).
    timings : dict of str to float
        Seconds per stage: ``preprocess``, ``target_sdf``, ``eigenbasis``, ``initialize``,
        ``optimize``, ``correspondence``; ``sdf_queries``: the part of ``optimize`` spent in
        source-SDF evaluations (the runs' and the comparisons'); with ``two_way``,
        ``two_way``: the part of ``optimize`` spent on the reverse registration and the run
        from its correspondences (whose SDF time is in ``sdf_queries`` too).
    metrics : dict of str to float
        Energies, RMS SDF residuals, surface distance and degeneracy
        (:func:`morphmodes_vol.metrics.shape_metrics`), ground-truth errors when a ground
        truth was given, landmark distances when landmarks were (``initial_landmark_rms``,
        ``landmark_rms`` in target units, ``landmark_rms_fraction`` of its diagonal).
        ``start``: the start whose run was kept (``rest`` or ``aligned``; with
        ``coarse_starts``, the coarse pass's runs are ``rest (coarse)`` and so on; with ``two_way``, ``reverse`` or ``reverse, both
        sides`` when a run from the reverse registration's correspondences was kept);
        ``starts``: one entry per run (``start``; the objective ``energy`` its run ended or
        was last judged with, on every node of the grid (``energy_grid`` ``"fine"``) or of the
        coarse pass's grid (``"coarse"``: a coarse run stopped early), or, for a lone run (one
        start, one pass), its final energy on its own quadrature (``"own"``; ``"fine"`` on the
        full grid), after
        ``energy_after_modes`` modes (both ``None`` and ``energy`` NaN when it never was);
        its ``edge_strain`` when it ended or stopped; ``evaluations``; and
        ``stopped_after_modes`` / ``stop_reason``, ``merged``, ``outstretched``,
        ``not chosen``, when it was stopped early; ``None`` otherwise); ``init_*``: the
        initial alignment (:meth:`InitialAlignment.summary`). Cost: ``evaluations_all_starts`` (every run's
        source-SDF evaluations; ``coarse_evaluations_all_starts`` of them on the
        coarse pass's grid), ``comparison_evaluations`` (the objectives that compared runs, on every
        node of the fine or the coarse grid, not among the former), ``points_queried``
        (every point sent to the source mesh's closest-point queries, the alignment's source
        field included) and ``full_grid_equivalents`` (that over the grid's nodes: the cost in
        evaluations of Eq. 3 on the full grid, each of which the ``paper`` preset makes); with
        ``two_way`` these include the reverse registration's, and ``two_way`` reports the
        choice (``kept``: ``"forward"``, ``"reverse"`` or ``"reverse, both sides"``;
        ``objectives``: each one's objective on the full grid; the reverse registration's
        kept ``reverse_registration_start``, its evaluations and seconds).
    correspondence_faces : (n,) int64 or None
        For every registered vertex, the closest target face (``None`` when the target was
        given as an SDF grid: it has no faces).
    correspondence_barycentrics : (n, 3) float64 or None
        Barycentric coordinates of the closest point on that face.
    normalization : Normalization
        The joint similarity from the original to the normalized frame.
    options : RegistrationOptions
    """

    vertices: np.ndarray
    faces: np.ndarray
    T: np.ndarray
    z: np.ndarray
    weights: np.ndarray
    eigenvalues: np.ndarray
    history: OptimizationHistory
    status: str
    timings: dict
    metrics: dict
    correspondence_faces: np.ndarray | None
    correspondence_barycentrics: np.ndarray | None
    normalization: Normalization
    options: RegistrationOptions
    target_vertices: np.ndarray = field(repr=False, default=None)
    target_faces: np.ndarray = field(repr=False, default=None)

    @property
    def evaluations(self) -> int:
        """Number of source-SDF evaluations on the quadrature, over every run, the coarse
        pass's included (``metrics["starts"]``; the initialization's coarse-grid evaluations are
        ``metrics["init_evaluations"]``, which sample a precomputed field, not the mesh)."""
        return int(self.metrics.get("evaluations_all_starts", self.history.evaluations))

    @property
    def modes(self) -> int:
        """Number of modes active at the end."""
        return int(self.T.shape[0])


class Registration:
    """State of one registration, built once: normalized meshes, grids, eigenbasis (first, so
    a source it cannot use fails early), target SDF.

    Parameters
    ----------
    source : path, trimesh.Trimesh or (V, F) tuple
    target : path, trimesh.Trimesh, (V, F) tuple, target-SDF file or TargetSDF
        A mesh, or its SDF: a ``.npz``/``.vdb`` path (:func:`~morphmodes_vol.sdf.load_target_sdf`)
        or a :class:`~morphmodes_vol.sdf.TargetSDF`. A target given as an SDF has no vertices:
        the joint normalization uses the box of its zero level set
        (``surface_bounds()``) in place of the target's vertices, the SDF is sampled in its own
        frame (``g = scale * sdf(undo(Q))``), and the result has no correspondence.
    options : RegistrationOptions, optional
    eigenbasis : SourceEigenbasis, optional
        A precomputed eigenbasis of this source (:func:`morphmodes_vol.stages.source_eigenbasis`,
        e.g. from a pipeline's cache), used instead of computing one in the pair's frame.
    target_sdf : TargetField, optional
        A precomputed target SDF of this target (:func:`morphmodes_vol.stages.target_field`),
        sampled at the quadrature points instead of building a dense grid over the pair's box.
    landmarks : CSV path, Landmarks or (indices (L,) int, points (L, 3) float), optional
        Source vertices pinned to target points (the target's original frame), added to
        Eq. (3) with ``options.landmark_weight`` (:mod:`morphmodes_vol.landmarks`).

    Examples
    --------
    >>> from morphmodes_vol.primitives import capsule
    >>> V, F = capsule(count=(8, 8))
    >>> reg = Registration((V, F), (V * [1.1, 1, 1], F), RegistrationOptions(grid=16, modes=2))
    >>> result = reg.run()
    >>> result.vertices.shape == V.shape
    True
    """

    def __init__(self, source: MeshLike, target: MeshLike, options: RegistrationOptions | None = None,
                 *, eigenbasis: SourceEigenbasis | None = None, target_sdf: TargetField | None = None,
                 landmarks: Landmarks | str | os.PathLike | tuple | None = None):
        self.options = options if options is not None else RegistrationOptions()
        self.asked_sign = self.options.source_sign  # "auto" is resolved per mesh below
        self.timings: dict[str, float] = {}
        self._objectives: dict = {}  # the comparison objectives' evaluators (_cached)
        self.runner = StartRunner(self)
        t = time.perf_counter()
        grid_target = self._preprocess(source, target, landmarks)
        self.timings["preprocess"] = time.perf_counter() - t
        t = time.perf_counter()
        self._eigenbasis(eigenbasis)
        self.timings["eigenbasis"] = time.perf_counter() - t
        log.info("%d skinning eigenmodes in %.2fs", self.options.modes, self.timings["eigenbasis"])
        t = time.perf_counter()
        self._target_field(target_sdf, grid_target)
        self.timings["target_sdf"] = time.perf_counter() - t
        log.info("target SDF (%s, %.1f MB), %d quadrature points, %.2fs",
                 type(self.target_sdf).__name__, self.target_sdf.nbytes / 1e6, self.Q.shape[0],
                 self.timings["target_sdf"])

    def _preprocess(self, source, target, landmarks):
        """Load and check the inputs, the joint normalized frame, the grids and the faces the
        SDFs use; returns the target when it was given as an SDF, else ``None``."""
        # 4 vertices: the least that determines the affine map of the first mode, and the
        # least that encloses a volume (a target needs an inside for its signed distance)
        self.source_vertices, self.source_faces = as_mesh(source, "source", min_vertices=4)
        target = scan_target(target, self.options)
        grid_target = as_target_sdf(target, self.options)
        if grid_target is None:
            self.target_vertices, self.target_faces = as_mesh(target, "target", min_vertices=4)
            target_box = self.target_vertices
        else:
            # an SDF has no vertices: its zero level set's box stands in for them
            self.target_vertices = self.target_faces = None
            target_box = np.stack(grid_target.surface_bounds())
        if self.options.modes > self.source_vertices.shape[0]:
            raise OptionError(
                f"modes={self.options.modes} exceeds the source's "
                f"{self.source_vertices.shape[0]} vertices"
            )
        if self.options.two_way and grid_target is not None:
            raise OptionError("two_way registers the target onto the source and needs the target "
                              "as a mesh; the target was given as an SDF")
        if self.options.two_way and self.options.modes > self.target_vertices.shape[0]:
            raise OptionError(f"two_way: modes={self.options.modes} exceeds the target's "
                              f"{self.target_vertices.shape[0]} vertices (the reverse "
                              "registration's source)")
        self.normalization = joint_normalization(self.source_vertices, target_box)
        self.landmarks = None if landmarks is None else as_landmarks(landmarks, len(self.source_vertices))
        self.X0 = self.normalization.apply(self.source_vertices)
        self.Y = None if grid_target is not None else self.normalization.apply(self.target_vertices)
        Yb = self.normalization.apply(target_box)
        lo = np.minimum(self.X0.min(axis=0), Yb.min(axis=0))
        hi = np.maximum(self.X0.max(axis=0), Yb.max(axis=0))
        pad = self.options.padding * float(np.linalg.norm(hi - lo))
        self.quadrature = Grid.covering(lo, hi, self.options.grid, pad)
        self.target_grid = Grid.covering(lo, hi, self.options.resolved_target_grid, pad)
        n_target_faces = 0 if self.target_faces is None else len(self.target_faces)
        check_memory(
            estimate_memory(len(self.source_vertices), len(self.source_faces), n_target_faces,
                            self.options.modes, self.quadrature.size, self.target_grid.size),
            self.options.memory_limit_gb,
            f"{_label(source, 'source')} ({len(self.source_vertices)} vertices) onto "
            f"{_label(target, 'target')} ({n_target_faces} faces) with {self.options.modes} "
            f"modes on a {'x'.join(map(str, self.quadrature.shape))} quadrature grid",
        )
        # faces for the SDFs and the eigenbasis: no degenerate or duplicate triangles,
        # consistent orientation (the output keeps the faces as given)
        self.source_sdf_faces = sdf_faces(self.X0, self.source_faces, "source")
        self.target_sdf_faces = None if self.Y is None else sdf_faces(self.Y, self.target_faces, "target")
        if self.options.source_sign == "auto":  # the options of this pair say which it is
            self.options = self.options.replace(source_sign=resolve_sign(self.source_sdf_faces, "auto"))
        elif self.options.source_sign == "raycast" and not is_closed(self.source_sdf_faces):
            log.warning(
                "the source mesh is not closed or has non-manifold edges (some edge is not "
                "shared by exactly two triangles): ray-parity signs may be wrong behind its "
                "holes; consider source_sign='winding'"
            )
        return grid_target

    def _eigenbasis(self, eigenbasis: SourceEigenbasis | None) -> None:
        """The skinning eigenmodes (Eq. 4) of the source, or a precomputed one moved to the
        pair's frame, and the basis ``B`` of ``x = B z + x0``."""
        if eigenbasis is None:
            self.weights, self.eigenvalues = mesh_skinning_weights(
                self.X0, self.source_sdf_faces, self.options.modes, seed=self.options.seed
            )
        else:
            expected = (self.source_vertices.shape[0], self.options.modes)
            if eigenbasis.weights.shape != expected:
                raise OptionError(
                    f"the precomputed eigenbasis has weights of shape {eigenbasis.weights.shape}, "
                    f"expected {expected} (source vertices, modes)"
                )
            self.weights, self.eigenvalues = eigenbasis.in_frame(self.normalization)
        self.basis = LBSBasis(self.X0, self.weights)

    def _target_field(self, target_sdf: TargetField | None, grid_target) -> None:
        """The target's SDF (built, cached or given), sampled at the quadrature points, and
        the confidence of an open target's field."""
        self.Q = self.quadrature.points()
        if target_sdf is not None:  # a cached field of this target mesh (pipelines)
            self.target_sdf = target_sdf
        elif grid_target is None:
            o = self.options
            self.target_sdf = build_target_sdf(self.Y, self.target_sdf_faces, self.target_grid,
                                               o.target_backend, o.target_sign, o.vdb_half_width)
        else:
            self.target_sdf = grid_target
        self.target_is_sdf = target_sdf is None and grid_target is not None
        self.g = self.sample_target(self.Q)
        # an open target's field is known near it and in front of it only (sdf/confidence.py)
        self.confidence = None if self.Y is None else target_confidence(
            self.Y, self.target_sdf_faces, self.target_grid,
            self.options.confidence_band_cells * self.quadrature.spacing)
        self.c = None if self.confidence is None else self.confidence.sample(self.Q)

    def energy(self) -> SDFEnergy:
        """A fresh evaluator of the objective for this pair (its evaluation counter starts
        at 0): Eq. (3) on the quadrature ``options.quadrature`` selects, plus the isometry
        prior and the landmarks when on."""
        return self.with_terms(self._quadrature_energy(self.quadrature, self.g, self.Q, c=self.c))

    def coarse_energy(self):
        """A fresh evaluator of the objective on every other node of the quadrature grid
        (spacing ``2h``, the fine grid's target values subsampled, band widths in its own
        cells), for the coarse pass of ``coarse_starts``."""
        return self.with_terms(self._coarse_sdf())

    def _coarse_sdf(self, kind: str | None = None) -> SDFEnergy:
        """Eq. (3) on every other node of the quadrature grid (spacing ``2h``, the fine
        grid's target values subsampled), on the quadrature ``kind`` (as
        :meth:`_quadrature_energy`)."""
        grid, idx = every_other_node(self.quadrature)
        return self._quadrature_energy(grid, self.g[idx], self.Q[idx], kind, None if self.c is None else self.c[idx])

    def with_terms(self, sdf):
        """``sdf`` (Eq. 3 on some quadrature) plus the terms the options and inputs add: the
        isometry prior (:mod:`morphmodes_vol.isometry`) and the landmarks
        (:mod:`morphmodes_vol.landmarks`), both weighted relative to the box's volume."""
        o = self.options
        volume = self.quadrature.cell_volume * self.Q.shape[0]
        if o.isometry_weight > 0:
            sdf = IsometryEnergy(sdf, self.X0, self.source_sdf_faces, o.isometry_weight, volume,
                                 o.isometry_tolerance)
        if self.landmarks is None or o.landmark_weight == 0:
            return sdf
        return LandmarkEnergy(sdf, self.landmarks.indices, self.normalization.apply(self.landmarks.points),
                              o.landmark_weight, volume)

    def _quadrature_energy(self, grid: Grid, g: np.ndarray, Q: np.ndarray,
                           kind: str | None = None, c: np.ndarray | None = None) -> SDFEnergy:
        """Eq. (3) on the nodes ``Q (N, 3)`` of ``grid`` (target values ``g (N,)``, the
        confidence of an open target's field ``c (N,)`` multiplying the weights), on the
        quadrature ``kind`` (default ``options.quadrature``); band widths are in cells of
        ``grid``. An open target's Eq. (3) is on every node whatever the quadrature: the
        unseen side of the source ends away from the observed surface, outside a band around
        it (docs/decisions/0021)."""
        o = self.options
        if (kind or o.quadrature) == "band" and c is None:
            Q, g, weight = band_quadrature(grid, g, self.sample_target, band=o.band_cells * grid.spacing,
                                           factor=o.block_factor, points=Q)
        else:
            weight = grid.cell_volume if c is None else grid.cell_volume * c
        return SDFEnergy(self.source_sdf_faces, Q, g, weight, sign=o.source_sign, samples=o.occupancy_samples)

    def sample_target(self, points: np.ndarray) -> np.ndarray:
        """Target SDF at ``points (k, 3)`` of the pair's normalized frame, ``(k,)``; its
        absolute value when the source's is unsigned (``source_sign="unsigned"``), so that
        every stage compares like with like."""
        g = self._target_values(points)
        return np.abs(g) if self.options.source_sign == "unsigned" else g

    def _target_values(self, points: np.ndarray) -> np.ndarray:
        if isinstance(self.target_sdf, TargetField):  # a pipeline's cached field
            return self.target_sdf.sample(points, self.normalization)
        if self.target_is_sdf:
            # an SDF given as a file lives in the target's original frame; distances scale
            n = self.normalization
            return n.scale * self.target_sdf.sample(n.undo(points))
        return self.target_sdf.sample(points)

    def save_target_sdf(self, path) -> Path:
        """Write the target's SDF to ``path`` (``.npz`` or ``.vdb``) in the target's original
        frame, so that ``register(source, path)`` registers onto the same target
        (:func:`morphmodes_vol.targets.save_target_sdf`). Returns the path."""
        return save_target_sdf(self, path)

    def initial_alignment(self) -> InitialAlignment:
        """The initialization stage (:func:`morphmodes_vol.initialize.align`) on a coarse grid
        of ``options.init_grid`` nodes over the pair's box."""
        o = self.options
        coarse = Grid.covering(self.quadrature.origin, self.quadrature.upper, o.init_grid)
        Q = coarse.points()
        weight = coarse.cell_volume if self.confidence is None else coarse.cell_volume * self.confidence.sample(Q)
        return align(self.X0, self.source_sdf_faces, Q, self.sample_target(Q), weight,
                     kind=o.initialization, keep=o.init_candidates,
                     sign=o.source_sign)

    def start_coefficients(self, matrix: np.ndarray) -> np.ndarray:
        """Mode 0's block ``(1, 3, 4)`` that maps the rest pose by ``x -> matrix @ [x, 1]``:
        mode 0 is constant, so ``T_0 = (A - [I 0]) / w_0``."""
        T0 = np.asarray(matrix, dtype=np.float64) - np.hstack([np.eye(3), np.zeros((3, 1))])
        return (T0 / self.weights[0, 0])[None]

    def runs_on_full_grid(self) -> bool:
        """Whether a run's own final energy is already the objective on the full grid."""
        return self.options.quadrature == "full" or self.c is not None  # an open target: every node

    def objective(self, X: np.ndarray) -> float:
        """The objective at the vertices ``X (n, 3)`` (normalized frame) with Eq. (3) on
        the full grid, comparable between runs."""
        return float(self._cached("full", lambda: self.with_terms(self.full_energy())).evaluate(X).energy)

    def coarse_objective(self, X: np.ndarray) -> float:
        """:meth:`objective` with Eq. (3) on every node of the coarse pass's grid (every
        other node of the quadrature grid): what the coarse pass compares its runs by."""
        evaluator = self._cached("coarse full", lambda: self.with_terms(self._coarse_sdf("full")))
        return float(evaluator.evaluate(X).energy)

    def _cached(self, name: str, build: Callable[[], object]) -> object:
        """An objective evaluator built once per options (its evaluations keep no state but
        counters)."""
        key = (name, self.options)
        if key not in self._objectives:
            self._objectives[key] = build()
        return self._objectives[key]

    def full_energy(self) -> SDFEnergy:
        """Eq. (3) on every node of the quadrature grid (the paper's quadrature)."""
        return self._quadrature_energy(self.quadrature, self.g, self.Q, "full", self.c)

    def run(
        self,
        progress: Callable[[ProgressEvent], None] | None = None,
        ground_truth: MeshLike | np.ndarray | None = None,
    ) -> RegistrationResult:
        """Optimize (Algorithm 1 from the starts, the warped pass, two-way when on) and
        assemble the result.

        Parameters
        ----------
        progress : callable, optional
            Receives a :class:`~morphmodes_vol.optimize.ProgressEvent` after every step.
        ground_truth : (n, 3) array, mesh or path, optional
            Where each source vertex should land (same vertex order); adds
            ``ground_truth_error`` and ``identity_error`` to the metrics.
        """
        timings = dict(self.timings)
        compared_before = comparison_counters(self._objectives.values())
        o = self._optimize(progress, timings)
        # the comparisons' objectives (full or coarse grid) are source-SDF queries too
        compared = np.subtract(comparison_counters(self._objectives.values()), compared_before)
        timings["sdf_queries"] = sum(r.sdf_seconds for r in o.runs) + float(compared[2])
        if o.rest_evaluator is not None:
            timings["sdf_queries"] += o.rest_evaluator.seconds
        if o.reverse is not None:
            timings["sdf_queries"] += o.reverse.timings["sdf_queries"]
        if len(o.runs) > 1:
            log.info("kept the start from the %s (edge strain %s, energy %s)", o.chosen.label,
                     ", ".join(f"{r.label} {r.strain:.3f}" for r in o.runs),
                     ", ".join(f"{r.label} {r.energy:.3g}" for r in o.runs))
        out = o.chosen.result
        vertices = self.normalization.undo(out.vertices)
        t = time.perf_counter()
        corr_faces, corr_bary, dist, diag = correspondence(self, out.vertices, vertices)
        timings["correspondence"] = time.perf_counter() - t
        metrics = result_metrics(self, o, out, dist, diag)
        metrics.update(cost_metrics(self, o, compared))
        if ground_truth is not None:
            truth = ground_truth if isinstance(ground_truth, np.ndarray) else as_mesh(ground_truth, "ground truth")[0]
            metrics["identity_error"] = ground_truth_error(self.source_vertices, truth)
            metrics["ground_truth_error"] = ground_truth_error(vertices, truth)
        if self.landmarks is not None:  # diag is normalized for a mesh target, original for an SDF
            metrics.update(landmark_metrics(self, vertices, diag / self.normalization.scale
                                            if self.Y is not None else diag))
        # surface distance and degeneracy (morphmodes_vol.metrics); a target given as an SDF
        # grid has no surface mesh to measure against
        if self.Y is not None:
            metrics.update(shape_metrics(self.X0, out.vertices, self.source_faces, self.Y, self.target_faces))
        return RegistrationResult(
            vertices=vertices, faces=self.source_faces.copy(), T=out.T, z=to_paper_z(out.T),
            weights=self.weights, eigenvalues=self.eigenvalues, history=out.history, status=out.status,
            timings=timings, metrics=metrics, correspondence_faces=corr_faces,
            correspondence_barycentrics=corr_bary, normalization=self.normalization, options=self.options,
            target_vertices=self.target_vertices, target_faces=self.target_faces,
        )

    def _optimize(self, progress, timings: dict) -> "Outcome":
        """The stages: the initialization and the starts, Algorithm 1 from them, the warped
        pass, two-way; ``timings`` gets each stage's seconds."""
        o = self.options
        # the warped pass's field runs need nothing from the runs of Algorithm 1, and its
        # descriptor channels nothing but the two meshes: on a second core they go on beside
        # the initialization and the runs (numpy, no source queries; the same results as one
        # after the other). BLAS runs on one thread throughout (morphmodes_vol.blas), so the
        # result does not depend on how many it would have.
        # (field_only: no runs to go beside, so no second thread)
        overlap = (ThreadPoolExecutor(1, thread_name_prefix="warped-field")
                   if o.warped_pass and o.overlap_field and not o.field_only else None)
        with single_threaded_blas():
            try:
                channels = (overlap.submit(descriptor_channels_or_error, self)
                            if overlap is not None and o.warped_descriptors and self.Y is not None else None)
                starts, candidates, init_summary, timings["initialize"] = self._starts()
                fields = (overlap.submit(warped_fields, self, starts, candidates, channels)
                          if overlap is not None else None)
                t = time.perf_counter()
                chosen, runs = (None, []) if o.field_only else self.runner.passes(starts, progress)
            finally:
                if overlap is not None:
                    overlap.shutdown(wait=True)
        outcome = Outcome(chosen, runs, init_summary)
        if o.warped_pass:
            t_warped = time.perf_counter()
            outcome.warped_field, warped_runs, outcome.warped, timings["warped_field"] = warped_pass(
                self, starts, chosen, progress, candidates, fields=None if fields is None else fields.result())
            outcome.keep(warped_runs, outcome.warped["kept"])
            timings["warped_pass"] = time.perf_counter() - t_warped
        if o.two_way:
            t_two_way = time.perf_counter()
            outcome.reverse, reverse_runs, outcome.two_way = two_way_pass(self, outcome.chosen, progress)
            outcome.keep(reverse_runs, outcome.two_way["kept"])
            timings["two_way"] = time.perf_counter() - t_two_way
        outcome.initial = outcome.runs[0].result.initial
        if o.field_only:
            # no run starts at the rest pose: the residual there, one evaluation of Eq. (3) on
            # the quadrature, is the report's initial one (and the failure warning's)
            outcome.rest_evaluator = self.energy()
            outcome.initial = outcome.rest_evaluator.evaluate(self.X0)
        timings["optimize"] = time.perf_counter() - t
        return outcome

    def _starts(self) -> tuple[list, list, dict, float]:
        """The starts of the runs (``(label, T0 or None, options)``: the rest pose, the SDF
        alignment and, when that turned the source, the unrotated alignment
        (:meth:`~morphmodes_vol.initialize.InitialAlignment.start_indices`), as the options
        ask), the initialization's other orientations
        for the warped pass (``(label, T0)``, ``warped_candidates``), the initialization's
        report and the seconds spent."""
        t = time.perf_counter()
        starts: list[tuple[str, np.ndarray | None, RegistrationOptions]] = [("rest", None, self.options)]
        init_summary = {}
        candidates = []  # the initialization's other orientations (warped_candidates)
        if self.options.initialization != "none":
            alignment = self.initial_alignment()
            init_summary = alignment.summary()
            own = alignment.start_indices()
            aligned = [(label, self.start_coefficients(alignment.refined_matrices[i]),
                        self.options) for label, i in own.items()]
            if self.options.warped_pass and self.options.warped_candidates:
                candidates = [(f"candidate {i}", self.start_coefficients(alignment.refined_matrices[i]))
                              for i in alignment.candidate_indices()]
            starts = starts + aligned if self.options.init_keep_rest else aligned
        return starts, candidates, init_summary, time.perf_counter() - t


def register(
    source: MeshLike,
    target: MeshLike,
    options: RegistrationOptions | None = None,
    *,
    progress: Callable[[ProgressEvent], None] | None = None,
    ground_truth: MeshLike | np.ndarray | None = None,
    landmarks: Landmarks | str | os.PathLike | tuple | None = None,
    **option_overrides,
) -> RegistrationResult:
    """Register ``source`` onto ``target`` by SDF matching in an adaptive skinning-eigenmode
    subspace (MorphModes, Algorithm 1).

    Parameters
    ----------
    source, target : path, trimesh.Trimesh or (V, F) tuple
        Triangle meshes. The source's vertex order is kept. The target may also be an SDF
        (``.npz``/``.vdb`` path or :class:`~morphmodes_vol.sdf.TargetSDF`), see
        :class:`Registration`.
    options : RegistrationOptions, optional
        All tunables; keyword overrides (``grid=48, modes=10``) are applied on top.
    progress : callable, optional
        Receives a :class:`~morphmodes_vol.optimize.ProgressEvent` after every step.
    ground_truth : optional
        Target positions of the source vertices (same order), for error metrics.
    landmarks : optional
        Source vertices pinned to target points (CSV path or ``(indices, points)``), see
        :class:`Registration`.

    Returns
    -------
    RegistrationResult

    Examples
    --------
    >>> from morphmodes_vol.primitives import capsule
    >>> V, F = capsule(count=(8, 8))
    >>> result = register((V, F), (V + [0.05, 0, 0], F), grid=16, modes=1)
    >>> result.vertices.shape
    (66, 3)
    """
    options = options if options is not None else RegistrationOptions()
    if option_overrides:
        options = options.replace(**option_overrides)
    return Registration(source, target, options, landmarks=landmarks).run(progress=progress,
                                                                         ground_truth=ground_truth)
