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
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import ArpackError

from .blas import single_threaded_blas
from .descriptors import heat_kernel_signature, surface_descriptor_grid
from .eigenbasis import LBSBasis, mesh_skinning_weights, to_paper_z
from .energy import SDFEnergy
from .errors import MeshValidationError, OptionError
from .initialize import InitialAlignment, align
from .isometry import IsometryEnergy
from .landmarks import LandmarkEnergy, Landmarks, as_landmarks, landmark_rms
from .mesh import MeshLike, Normalization, as_mesh, bbox_diagonal, joint_normalization
from .limits import check_memory, estimate_memory
from .metrics import edge_strain, ground_truth_error, shape_metrics
from .options import RegistrationOptions
from .quadrature import BandEnergy, CoarseToFine, every_other_node
from .repair import sdf_faces
from .optimize import AdaptiveRun, OptimizationHistory, ProgressEvent
from .pointcloud import PointCloud, as_point_cloud, is_point_cloud_file, load_point_cloud, oriented_normals
from .sdf import Grid, TargetSDF, build_target_sdf, closest_points, is_target_sdf_path, load_target_sdf
from .sdf.confidence import target_confidence
from .sdf.grid import trilinear_sample
from .sdf.points import points_target_sdf, poisson_depth, poisson_surface
from .sdf.source import is_closed, resolve_sign
from .sdf.target import TARGET_SDF_SUFFIXES, DenseTargetSDF, target_sdf_backend
from .stages import SourceEigenbasis, TargetField
from .two_way import reverse_correspondences, closest_point_rows
from .warped_field import WarpedRestField, ZeroEnergy

__all__ = ["register", "Registration", "RegistrationResult", "ground_truth_error", "scan_target"]

log = logging.getLogger(__name__)


COARSE_SUFFIX = " (coarse)"
"""Added to a start's name for its run in the coarse pass (``coarse_starts``)."""
WARPED_PREFIX = "warped: "
"""Put before a start's name for the run refined from the warped rest field (``warped_pass``)."""
DESCRIPTOR_ERRORS = (MeshValidationError, ArpackError, np.linalg.LinAlgError)
"""Why a descriptor field may not be built (logged, and the descriptor hop skipped)."""

MIN_COARSE_NODES = 24
"""Fewest nodes along the longest side of the coarse pass's grid (``coarse_starts``), so
grids under 48 nodes run one pass: at grid 32 (a coarse pass of 16 nodes) lion-05 ended at
0.109 against 0.018 in one pass, at 48 and 64 at 0.013 and 0.017."""


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
        source-SDF evaluations; ``coarse_evaluations_all_starts`` and
        ``partial_evaluations_all_starts`` of them on the coarse pass's grid and after band
        refreshes), ``comparison_evaluations`` (the objectives that compared runs, on every
        node of the fine or the coarse grid, not among the former), ``points_queried``
        (every point sent to the source mesh's closest-point queries, the alignment's source
        field included) and ``full_grid_equivalents`` (that over the grid's nodes: the cost in
        evaluations of Eq. 3 on the full grid, each of which ``--optimizer paper`` makes); with
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
        self._asked_sign = self.options.source_sign  # "auto" is resolved per mesh below
        self.timings: dict[str, float] = {}
        self._objectives: dict = {}  # the comparison objectives' evaluators (_cached)

        t = time.perf_counter()
        # 4 vertices: the least that determines the affine map of the first mode, and the
        # least that encloses a volume (a target needs an inside for its signed distance)
        self.source_vertices, self.source_faces = as_mesh(source, "source", min_vertices=4)
        target = scan_target(target, self.options)
        grid_target = _as_target_sdf(target, self.options)
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
        self.timings["preprocess"] = time.perf_counter() - t

        t = time.perf_counter()
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
        self.timings["eigenbasis"] = time.perf_counter() - t
        log.info("%d skinning eigenmodes in %.2fs", self.options.modes, self.timings["eigenbasis"])

        t = time.perf_counter()
        self.Q = self.quadrature.points()
        if target_sdf is not None:  # a cached field of this target mesh (pipelines)
            self.target_sdf = target_sdf
        elif grid_target is None:
            o = self.options
            self.target_sdf = build_target_sdf(self.Y, self.target_sdf_faces, self.target_grid,
                                               o.target_backend, o.target_sign, o.vdb_half_width)
        else:
            self.target_sdf = grid_target
        self._grid_target = target_sdf is None and grid_target is not None
        self.g = self.sample_target(self.Q)
        # an open target's field is known near it and in front of it only (sdf/confidence.py)
        self.confidence = None if self.Y is None else target_confidence(
            self.Y, self.target_sdf_faces, self.target_grid, self.options.band_cells * self.quadrature.spacing)
        self.c = None if self.confidence is None else self.confidence.sample(self.Q)
        self.timings["target_sdf"] = time.perf_counter() - t
        log.info("target SDF (%s, %.1f MB), %d quadrature points, %.2fs",
                 type(self.target_sdf).__name__, self.target_sdf.nbytes / 1e6, self.Q.shape[0],
                 self.timings["target_sdf"])

    def energy(self) -> SDFEnergy | BandEnergy:
        """A fresh evaluator of the objective for this pair (its evaluation counter starts
        at 0): Eq. (3) on the quadrature ``options.quadrature`` selects, plus the isometry
        prior and the landmarks when on."""
        o = self.options
        sdf = self._quadrature_energy(self.quadrature, self.g, self.Q, c=self.c)
        if o.coarse_modes > 0:
            # a grid refining across stages: every other node (spacing 2h) for the first
            # coarse_modes stages
            sdf = CoarseToFine(self._coarse_sdf(), sdf, o.coarse_modes)
        return self._with_terms(sdf)

    def coarse_energy(self):
        """A fresh evaluator of the objective on every other node of the quadrature grid
        (spacing ``2h``, the fine grid's target values subsampled, band widths in its own
        cells), for the coarse pass of ``coarse_starts``."""
        return self._with_terms(self._coarse_sdf())

    def _coarse_sdf(self, kind: str | None = None) -> SDFEnergy | BandEnergy:
        """Eq. (3) on every other node of the quadrature grid (spacing ``2h``, the fine
        grid's target values subsampled), on the quadrature ``kind`` (as
        :meth:`_quadrature_energy`)."""
        grid, idx = every_other_node(self.quadrature)
        return self._quadrature_energy(grid, self.g[idx], self.Q[idx], kind, None if self.c is None else self.c[idx])

    def _with_terms(self, sdf):
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
                           kind: str | None = None, c: np.ndarray | None = None) -> SDFEnergy | BandEnergy:
        """Eq. (3) on the nodes ``Q (N, 3)`` of ``grid`` (target values ``g (N,)``, the
        confidence of an open target's field ``c (N,)`` multiplying the weights), on the
        quadrature ``kind`` (default ``options.quadrature``); band widths are in cells of
        ``grid``."""
        o = self.options
        if (kind or o.quadrature) == "band":
            h = grid.spacing
            return BandEnergy(
                self.source_sdf_faces, grid, g, self.sample_target,
                band=o.band_cells * h, factor=o.block_factor, margin=o.band_margin_cells * h,
                sign=o.source_sign, samples=o.occupancy_samples, points=Q,
                confidence=None if c is None else (c, self.confidence.sample),
            )
        weight = grid.cell_volume if c is None else grid.cell_volume * c
        return SDFEnergy(self.source_sdf_faces, Q, g, weight, sign=o.source_sign, samples=o.occupancy_samples)

    def sample_target(self, points: np.ndarray) -> np.ndarray:
        """Target SDF at ``points (k, 3)`` of the pair's normalized frame, ``(k,)``."""
        if isinstance(self.target_sdf, TargetField):  # a pipeline's cached field
            return self.target_sdf.sample(points, self.normalization)
        if self._grid_target:
            # an SDF given as a file lives in the target's original frame; distances scale
            n = self.normalization
            return n.scale * self.target_sdf.sample(n.undo(points))
        return self.target_sdf.sample(points)

    def save_target_sdf(self, path) -> Path:
        """Write the target's SDF to ``path`` (``.npz``: dense grid, ``.vdb``: OpenVDB level
        set) in the target's original frame, so that ``register(source, path)`` registers onto
        the same target. Returns the path.

        ``target_sdf`` itself is in the pair's normalized frame when the target is a mesh (and
        in the target's own frame for a pipeline's cached field): saved as it is, its target
        would sit at another place and scale. A dense grid built here is moved to the original
        frame exactly (nodes mapped back, spacing and values divided by the normalization's
        scale); an OpenVDB level set, or a pipeline's field, is rebuilt from the target mesh on
        the same lattice mapped back; a target given as an SDF is written as it was read, to a
        file of its own kind.

        Examples
        --------
        >>> import tempfile, pathlib
        >>> from morphmodes_vol.primitives import capsule
        >>> from morphmodes_vol.sdf import load_target_sdf
        >>> V, F = capsule(count=(8, 8))
        >>> reg = Registration((V, F), (V * 3.0 + 5.0, F), RegistrationOptions(grid=16, modes=2))
        >>> path = reg.save_target_sdf(pathlib.Path(tempfile.mkdtemp()) / "target.npz")
        >>> lo, hi = load_target_sdf(path).surface_bounds()  # the target's box, [4.25, 5.75] x ... x [2.75, 7.25]
        >>> np.round(lo, 1).tolist(), np.round(hi, 1).tolist()
        ([4.3, 4.3, 2.8], [5.7, 5.7, 7.2])
        """
        path = Path(path)
        backend = target_sdf_backend(path)
        sdf = self.target_sdf
        if self._grid_target:  # read from a file, in the target's original frame already
            kind = "dense" if isinstance(sdf, DenseTargetSDF) else "vdb"
            if kind != backend:
                suffix = next(s for s, b in TARGET_SDF_SUFFIXES.items() if b == kind)
                raise OptionError(f"{path}: the target was given as a {kind} SDF; write it to a "
                                  f"{suffix} file")
            sdf.save(path)
            return path
        n, g, o = self.normalization, self.target_grid, self.options
        grid = Grid(origin=n.undo(g.origin[None])[0], spacing=g.spacing / n.scale, shape=g.shape)
        if backend == "dense" and isinstance(sdf, DenseTargetSDF):
            out = DenseTargetSDF(grid, sdf.values / n.scale)
        else:
            log.info("target SDF: rebuilt in the target's frame for %s", path)
            out = build_target_sdf(self.target_vertices, self.target_sdf_faces, grid, backend,
                                   o.target_sign, o.vdb_half_width)
        out.save(path)
        return path

    def initial_alignment(self) -> InitialAlignment:
        """The initialization stage (:func:`morphmodes_vol.initialize.align`) on a coarse grid
        of ``options.init_grid`` nodes over the pair's box."""
        o = self.options
        coarse = Grid.covering(self.quadrature.origin, self.quadrature.upper, o.init_grid)
        Q = coarse.points()
        weight = coarse.cell_volume if self.confidence is None else coarse.cell_volume * self.confidence.sample(Q)
        return align(self.X0, self.source_sdf_faces, Q, self.sample_target(Q), weight,
                     kind=o.initialization, keep=o.init_candidates, switch=o.init_switch,
                     sign=o.source_sign)

    def _start_coefficients(self, matrix: np.ndarray) -> np.ndarray:
        """Mode 0's block ``(1, 3, 4)`` that maps the rest pose by ``x -> matrix @ [x, 1]``:
        mode 0 is constant, so ``T_0 = (A - [I 0]) / w_0``."""
        T0 = np.asarray(matrix, dtype=np.float64) - np.hstack([np.eye(3), np.zeros((3, 1))])
        return (T0 / self.weights[0, 0])[None]

    def _runs_on_full_grid(self) -> bool:
        """Whether a run's own final energy is already the objective on the full grid."""
        return self.options.quadrature == "full" and self.options.coarse_modes == 0

    def _comparable_energy(self, r: "_StartRun") -> float:
        """The objective of a finished run's result (Eq. 3 plus the isometry prior and
        landmarks when on) with Eq. (3) on the full grid: its own final energy when it ran
        there, else evaluated (a band quadrature differs per run; the coarse pass runs on
        every other node)."""
        if self._runs_on_full_grid() and r.objective is None:
            return float(r.result.final.energy)
        return self._objective(r.result.vertices)

    def _objective(self, X: np.ndarray) -> float:
        """The objective at the vertices ``X (n, 3)`` (normalized frame) with Eq. (3) on
        the full grid, comparable between runs."""
        return float(self._cached("full", lambda: self._with_terms(self.full_energy())).evaluate(X).energy)

    def _coarse_objective(self, X: np.ndarray) -> float:
        """:meth:`_objective` with Eq. (3) on every node of the coarse pass's grid (every
        other node of the quadrature grid): what the coarse pass compares its runs by."""
        evaluator = self._cached("coarse full", lambda: self._with_terms(self._coarse_sdf("full")))
        return float(evaluator.evaluate(X).energy)

    def _cached(self, name: str, build: Callable[[], object]) -> object:
        """An objective evaluator built once per options (its evaluations keep no state but
        counters)."""
        key = (name, self.options)
        if key not in self._objectives:
            self._objectives[key] = build()
        return self._objectives[key]

    def _run_starts(self, starts, progress, energy=None, objective=None,
                    judge: bool = True) -> list["_StartRun"]:
        """Algorithm 1 from every start, advanced in lockstep one stage (mode) at a time.

        After each stage from ``start_check_modes`` on, a run stops early when another
        makes it redundant (docs/method.md, "Initialization and two starts", item 6),
        pair by pair:

        - *merged*: the two runs' vertices are closer than ``start_merge_distance`` (RMS,
          normalized units) to each other; the one that stretches the edges more stops;
        - *outstretched*: a run's edge strain is more than ``start_strain_ratio`` times the
          other's, and the other's objective (``objective``) is within ``select_energy_factor``
          of its own: the final selection (:func:`_select_start`) would not keep it.

        After ``start_choice_modes`` modes, the final selection is made among the runs
        still going, and the others stop (*not chosen*). ``energy``: the evaluator factory
        (default :meth:`energy`); ``objective``: what the runs are compared by while they
        run (default :meth:`_objective`, Eq. 3 on the full grid; the coarse pass gives
        :meth:`_coarse_objective`, and the report names the grid accordingly). A run that
        ends is judged by :meth:`_objective` whatever ``objective`` is; ``judge=False`` (a
        lone run that nothing is chosen against) keeps its own final energy instead, on its
        quadrature, and saves that evaluation.
        """
        o = self.options
        live = []
        for label, start, options in starts:
            if len(starts) > 1:
                log.info("Algorithm 1 from start %s", label)
            evaluator = (energy or self.energy)()
            shown = progress if progress is None or len(starts) == 1 else _labelled(progress, label)
            live.append(_StartRun(label, None, 0.0, float("nan"), float("nan"), energy_term=evaluator,
                                  objective=objective,
                                  run=AdaptiveRun(evaluator, self.basis, options, shown, start)))
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
                            self._redundant_start(a, b)
                    going = [r for r in going if r.stopped is None]
                if len(going) > 1 and o.start_choice_modes is not None and stage >= o.start_choice_modes:
                    self._choose_now(going)
                for r in [r for r in live if r.run.done or r.stopped is not None]:
                    self._finish(r, judge)
                    live.remove(r)
        return runs

    def _finish(self, r: "_StartRun", judge: bool = True) -> None:
        """Keep a run's result, SDF time, edge strain and (when it ran to the end) objective
        (``judge=False``: its final energy on its own quadrature); let its evaluator go."""
        self._state_of(r)  # the strain at the run's last state
        r.result = r.run.result()
        r.sdf_seconds = r.energy_term.seconds
        r.points_queried = _points_queried(r.energy_term)
        if r.stopped is None and not judge:
            r.energy, r.judged = float(r.result.final.energy), r.run.stage
            r.energy_grid = "fine" if self._runs_on_full_grid() and r.objective is None else "own"
        elif r.stopped is None:  # a stopped run keeps the objective it was judged by (or NaN)
            r.energy = self._comparable_energy(r)
            r.judged, r.energy_grid = r.run.stage, "fine"
        r.run = r.energy_term = r.vertices = r.objective = None

    def _state_of(self, r: "_StartRun") -> np.ndarray:
        """A running start's vertices ``(n, 3)`` now, its edge strain left in ``r.strain``;
        computed once per stage, however many pairs and choices ask."""
        if r.seen != r.run.stage:
            r.seen, r.vertices = r.run.stage, r.run.vertices
            r.strain = edge_strain(self.X0, r.vertices, self.source_faces)
        return r.vertices

    def _objective_of(self, r: "_StartRun") -> float:
        """The objective (``r.objective``, else :meth:`_objective`) of a running start's
        current state, computed once per stage."""
        if r.judged != r.run.stage:
            r.judged, r.energy = r.run.stage, (r.objective or self._objective)(self._state_of(r))
            r.energy_grid = "fine" if r.objective is None else "coarse"
        return r.energy

    def _full_grid_objective(self, r: "_StartRun") -> float:
        """A finished run's objective on the full grid: its energy when it was judged there,
        else :meth:`_objective` of its result."""
        return r.energy if r.energy_grid == "fine" else self._objective(r.result.vertices)

    def _redundant_start(self, a: "_StartRun", b: "_StartRun") -> "_StartRun | None":
        """The run of ``a``, ``b`` (at the same stage) that need not go on, or ``None``;
        marks it stopped."""
        o = self.options
        Xa, Xb = self._state_of(a), self._state_of(b)
        sa, sb = a.strain, b.strain
        stage = a.run.stage
        distance = _rms(Xa - Xb)
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

    def _choose_now(self, runs: list["_StartRun"]) -> "_StartRun":
        """The final selection (:func:`_select_start`) among ``runs`` (at the same stage),
        made now: the others are marked stopped (*not chosen*); returns the kept run."""
        for r in runs:
            self._objective_of(r)  # and the strain, by _state_of
        kept = _select_start(runs, self.options.select_energy_factor)
        for r in runs:
            if r is not kept:
                r.stopped, r.reason = r.run.stage, "not chosen"
        log.info("after %d modes the start from the %s is kept (edge strain %s; objective %s)",
                 kept.run.stage, kept.label, ", ".join(f"{r.label} {r.strain:.3f}" for r in runs),
                 ", ".join(f"{r.label} {r.energy:.3g}" for r in runs))
        return kept

    def full_energy(self) -> SDFEnergy:
        """Eq. (3) on every node of the quadrature grid (the paper's quadrature)."""
        return self._quadrature_energy(self.quadrature, self.g, self.Q, "full", self.c)

    def run(
        self,
        progress: Callable[[ProgressEvent], None] | None = None,
        ground_truth: MeshLike | np.ndarray | None = None,
    ) -> RegistrationResult:
        """Optimize (Algorithm 1) and assemble the result.

        Parameters
        ----------
        progress : callable, optional
            Receives a :class:`~morphmodes_vol.optimize.ProgressEvent` after every step.
        ground_truth : (n, 3) array, mesh or path, optional
            Where each source vertex should land (same vertex order); adds
            ``ground_truth_error`` and ``identity_error`` to the metrics.
        """
        timings = dict(self.timings)
        compared_before = _comparison_counters(self._objectives.values())
        # the warped pass's field runs need nothing from the runs of Algorithm 1, and its
        # descriptor channels nothing but the two meshes: on a second core they go on beside
        # the initialization and the runs (numpy, no source queries; the same results as one
        # after the other). BLAS runs on one thread throughout (morphmodes_vol.blas), so the
        # result does not depend on how many it would have.
        # (field_only: no runs to go beside, so no second thread)
        overlap = (ThreadPoolExecutor(1, thread_name_prefix="warped-field")
                   if self.options.warped_pass and self.options.overlap_field and not self.options.field_only
                   else None)
        with single_threaded_blas():
            try:
                channels = (overlap.submit(self._descriptor_channels_or_error)
                            if overlap is not None and self.options.warped_descriptors and self.Y is not None
                            else None)
                starts, candidates, init_summary, timings["initialize"] = self._starts()
                fields = (overlap.submit(self._warped_fields, starts, candidates, channels)
                          if overlap is not None else None)
                t = time.perf_counter()
                chosen, runs = (None, []) if self.options.field_only else self._passes(starts, progress)
            finally:
                if overlap is not None:
                    overlap.shutdown(wait=True)
        warped_field, warped = None, {}
        if self.options.warped_pass:
            t_warped = time.perf_counter()
            warped_field, warped_runs, warped, timings["warped_field"] = self._warped_pass(
                starts, chosen, progress, candidates, fields=None if fields is None else fields.result())
            runs += warped_runs
            chosen = next((r for r in warped_runs if r.label == warped["kept"]), chosen)
            timings["warped_pass"] = time.perf_counter() - t_warped
        reverse, two_way = None, {}
        if self.options.two_way:
            t_two_way = time.perf_counter()
            reverse, reverse_runs, two_way = self._two_way(chosen, progress)
            runs += reverse_runs
            chosen = next((r for r in reverse_runs if r.label == two_way["kept"]), chosen)
            timings["two_way"] = time.perf_counter() - t_two_way
        out, first = chosen.result, runs[0].result
        initial, rest_evaluator = first.initial, None
        if self.options.field_only:
            # no run starts at the rest pose: the residual there, one evaluation of Eq. (3) on
            # the quadrature, is the report's initial one (and the failure warning's)
            rest_evaluator = self.energy()
            initial = rest_evaluator.evaluate(self.X0)
        timings["optimize"] = time.perf_counter() - t
        # the comparisons' objectives (full or coarse grid) are source-SDF queries too
        compared = np.subtract(_comparison_counters(self._objectives.values()), compared_before)
        timings["sdf_queries"] = sum(r.sdf_seconds for r in runs) + float(compared[2])
        if rest_evaluator is not None:
            timings["sdf_queries"] += rest_evaluator.seconds
        if reverse is not None:
            timings["sdf_queries"] += reverse.timings["sdf_queries"]
        if len(runs) > 1:
            log.info("kept the start from the %s (edge strain %s, energy %s)", chosen.label,
                     ", ".join(f"{r.label} {r.strain:.3f}" for r in runs),
                     ", ".join(f"{r.label} {r.energy:.3g}" for r in runs))

        vertices = self.normalization.undo(out.vertices)

        t = time.perf_counter()
        if self.Y is not None:
            # in the normalized frame (Open3D searches in float32); barycentrics and face ids
            # are invariant under the similarity, distances scale by 1 / normalization.scale
            cp = closest_points(self.Y, self.target_faces, out.vertices)
            corr_faces, corr_bary, dist, diag = cp.faces, cp.barycentrics, cp.distance, bbox_diagonal(self.Y)
        else:
            # no target faces: the distance is |target SDF| at the registered vertices, over
            # the diagonal of the zero level set's box (both in the target's frame)
            corr_faces = corr_bary = None
            dist = np.abs(self.target_sdf.sample(vertices))
            diag = float(np.linalg.norm(np.subtract(*self.target_sdf.surface_bounds())))
        timings["correspondence"] = time.perf_counter() - t

        metrics = {
            # at the rest pose when a run started there (the aligned start's is better
            # already); with field_only at the rest pose
            "initial_energy": float(initial.energy),
            "final_energy": float(out.final.energy),
            "initial_sdf_rms": initial.rms_residual,
            "final_sdf_rms": out.final.rms_residual,
            "sdf_rms_units": "fraction of the union bounding-box diagonal",
            "mean_distance_to_target": float(dist.mean() / diag),
            "target_sdf_bytes": int(self.target_sdf.nbytes),
        }
        if metrics["final_sdf_rms"] > 0.5 * metrics["initial_sdf_rms"]:
            log.warning(
                "the SDF residual fell only from %.3g to %.3g: the registration may have "
                "failed (source and target far apart or very differently oriented?)",
                metrics["initial_sdf_rms"], metrics["final_sdf_rms"],
            )
        metrics.update(init_summary)
        if warped:
            metrics["warped_pass"] = warped
        if two_way:
            metrics["two_way"] = two_way
        metrics["edge_strain"] = chosen.strain
        metrics["start"] = chosen.label
        metrics["starts"] = [{"start": r.label, "energy": r.energy, "energy_grid": r.energy_grid,
                              "energy_after_modes": r.judged if r.energy_grid else None,
                              "edge_strain": r.strain,
                              "evaluations": r.result.history.evaluations,
                              "stopped_after_modes": r.stopped, "stop_reason": r.reason}
                             for r in runs]
        # with two_way, the counts below include the reverse registration's (it queries the
        # target mesh, on a grid of the same box)
        rm = {} if reverse is None else reverse.metrics
        metrics["evaluations_all_starts"] = (sum(r.result.history.evaluations for r in runs)
                                             + rm.get("evaluations_all_starts", 0))
        # of which on the coarse pass's grid (coarse_starts), each a few times cheaper
        metrics["coarse_evaluations_all_starts"] = (sum(r.result.history.evaluations for r in runs
                                                        if r.label.endswith(COARSE_SUFFIX))
                                                    + rm.get("coarse_evaluations_all_starts", 0))
        # of which after a band refresh, querying only the points new to the band
        metrics["partial_evaluations_all_starts"] = (sum(r.result.history.partial_evaluations for r in runs)
                                                     + rm.get("partial_evaluations_all_starts", 0))
        # the objectives that compared runs (every node of the fine or the coarse grid),
        # not counted above
        metrics["comparison_evaluations"] = int(compared[0]) + rm.get("comparison_evaluations", 0)
        # every point sent to the source mesh's closest-point queries: the runs' evaluations
        # and band refreshes, the comparisons, the initial alignment's source field; over the
        # grid's nodes, the cost in evaluations of Eq. (3) on the full grid (the paper's)
        queried = (sum(r.points_queried for r in runs) + int(compared[1])
                   + int(init_summary.get("init_field_nodes", 0)) + rm.get("points_queried", 0)
                   + (warped_field.nodes_queried if warped_field is not None else 0)
                   + (_points_queried(rest_evaluator) if rest_evaluator is not None else 0))
        metrics["points_queried"] = queried
        metrics["full_grid_equivalents"] = queried / self.Q.shape[0]
        if ground_truth is not None:
            truth = ground_truth if isinstance(ground_truth, np.ndarray) else as_mesh(ground_truth, "ground truth")[0]
            metrics["identity_error"] = ground_truth_error(self.source_vertices, truth)
            metrics["ground_truth_error"] = ground_truth_error(vertices, truth)
        if self.landmarks is not None:  # diag is normalized for a mesh target, original for an SDF
            metrics.update(self._landmark_metrics(vertices, diag / self.normalization.scale
                                                  if self.Y is not None else diag))
        # surface distance and degeneracy (morphmodes_vol.metrics); a target given as an SDF
        # grid has no surface mesh to measure against
        if self.Y is not None:
            metrics.update(shape_metrics(self.X0, out.vertices, self.source_faces, self.Y, self.target_faces))

        return RegistrationResult(
            vertices=vertices,
            faces=self.source_faces.copy(),
            T=out.T,
            z=to_paper_z(out.T),
            weights=self.weights,
            eigenvalues=self.eigenvalues,
            history=out.history,
            status=out.status,
            timings=timings,
            metrics=metrics,
            correspondence_faces=corr_faces,
            correspondence_barycentrics=corr_bary,
            normalization=self.normalization,
            options=self.options,
            target_vertices=self.target_vertices,
            target_faces=self.target_faces,
        )

    def _starts(self) -> tuple[list, list, dict, float]:
        """The starts of the runs (``(label, T0 or None, options)``: the rest pose, the SDF
        alignment, as the options ask), the initialization's other orientations
        for the warped pass (``(label, T0)``, ``warped_candidates``), the initialization's
        report and the seconds spent."""
        t = time.perf_counter()
        starts: list[tuple[str, np.ndarray | None, RegistrationOptions]] = [("rest", None, self.options)]
        init_summary = {}
        candidates = []  # the initialization's other orientations (warped_candidates)
        if self.options.initialization != "none":
            aligned_options = self.options.replace(
                lm_iterations_per_stage=self.options.init_lm_iterations_per_stage)
            alignment = self.initial_alignment()
            init_summary = alignment.summary()
            aligned = [("aligned", self._start_coefficients(alignment.matrix), aligned_options)]
            if self.options.warped_pass and self.options.warped_candidates:
                candidates = [(f"candidate {i}", self._start_coefficients(M))
                              for i, M in alignment.refined_matrices.items() if i != alignment.chosen]
            starts = starts + aligned if self.options.init_keep_rest else aligned
        return starts, candidates, init_summary, time.perf_counter() - t

    def _two_way(self, forward: "_StartRun", progress) -> tuple["RegistrationResult", list["_StartRun"], dict]:
        """``two_way`` (docs/method.md, "Two-way registration"): register the target onto the
        source, fit the subspace to the correspondences it implies, in two ways: the source
        vertices' counterparts on the target
        (:func:`~morphmodes_vol.two_way.reverse_correspondences`), and those stacked with the
        target vertices' counterparts on the source's surface
        (:func:`~morphmodes_vol.two_way.closest_point_rows`); minimize the objective from
        each fit on all modes (one stage of at most ``two_way_iterations`` Levenberg-Marquardt
        steps); and compare with the ``forward`` run's result by the objective on the full
        grid. Returns the reverse registration, the two runs and the report
        (``metrics["two_way"]``)."""
        o = self.options
        log.info("two-way: registering the target onto the source")
        grid = o.grid if o.two_way_grid is None else o.two_way_grid
        reverse = Registration((self.target_vertices, self.target_faces),
                               (self.source_vertices, self.source_faces),
                               o.replace(two_way=False, grid=grid, source_sign=self._asked_sign))
        shown = None if progress is None else (  # "[reverse: rest (coarse)] ..." and so on
            lambda e: progress(replace(e, start=f"reverse: {e.start}" if e.start else "reverse")))
        back = reverse.run(progress=shown)
        # the reverse result lies on the source's surface, in the source's original frame
        Yd = self.normalization.apply(back.vertices)
        P = reverse_correspondences(self.X0, Yd, self.target_faces, self.Y)
        S = closest_point_rows(self.X0, self.source_sdf_faces, Yd)
        both = sp.vstack([sp.identity(self.X0.shape[0], format="csr"), S], format="csr")
        fits = {"reverse": self.basis.fit(P, o.modes),
                "reverse, both sides": self.basis.fit(np.vstack([P, self.Y]), o.modes, rows=both)}
        options = o.replace(initial_modes=o.modes, lm_final_iterations=o.two_way_iterations)
        runs = self._run_starts([(label, T, options) for label, T in fits.items()], progress)
        objectives = {"forward": self._full_grid_objective(forward), **{r.label: r.energy for r in runs}}
        finite = {k: e for k, e in objectives.items() if np.isfinite(e)}
        kept = min(finite, key=finite.get) if finite else "forward"
        log.info("two-way: objective %s: kept the %s result",
                 ", ".join(f"{k} {e:.4g}" for k, e in objectives.items()), kept)
        report = {"kept": kept, "objectives": objectives,
                  "reverse_registration_start": back.metrics["start"],
                  "reverse_registration_evaluations": back.evaluations,
                  "reverse_registration_seconds": float(sum(v for k, v in back.timings.items()
                                                            if k != "sdf_queries"))}
        return back, runs, report

    def _passes(self, starts, progress) -> tuple["_StartRun", list["_StartRun"]]:
        """Algorithm 1 from the starts: with ``coarse_starts``, every start on the coarse grid
        (every other node), else on the grid. Returns the run chosen and every run."""
        factor = self.options.select_energy_factor
        coarse_pass = self.options.coarse_starts and max(self.quadrature.shape) >= 2 * MIN_COARSE_NODES
        if self.options.coarse_starts and not coarse_pass:
            log.info("grid of %d nodes: too coarse for a coarse pass (coarse_starts)", max(self.quadrature.shape))
        if coarse_pass:
            # every start on the coarse grid; the grid itself is the warped pass's, whose
            # refinements run on it (docs/decisions/0004)
            coarse = [(label + COARSE_SUFFIX, start, options) for label, start, options in starts]
            runs = self._run_starts(coarse, progress, self.coarse_energy, self._coarse_objective)
            chosen = _select_start([r for r in runs if r.stopped is None], factor)
        else:
            # a lone run is not compared with anything (unless two_way compares it with the
            # run from the reverse registration): no objective on the full grid
            runs = self._run_starts(starts, progress, judge=len(starts) > 1 or self.options.two_way
                                    or self.options.warped_pass)
            chosen = _select_start([r for r in runs if r.stopped is None], factor)
        return chosen, runs

    def _warped_fields(self, starts, candidates=(), descriptors=None) -> "_WarpedFields":
        """The warped pass's field runs (``warped_pass``; :meth:`_warped_pass`): the field
        built once, minimized from every start and from ``candidates`` (``(label, T0)``;
        one that maps the source within ``start_merge_distance`` of a start already taken is
        skipped) to ``warped_prune_modes`` modes, then from those of field energy within
        ``warped_prune_ratio`` of the lowest to the end; with ``descriptors`` (the future of
        :meth:`_descriptor_channels_or_error`), also the descriptor field
        (:meth:`_descriptor_field`, or the error that stopped it). No source query after the
        field's one at the start, and nothing from the runs on Eq. (3): :meth:`run` lets it
        go on beside them (``overlap_field``)."""
        o = self.options
        h = self.quadrature.spacing
        field = WarpedRestField(self.basis, self.source_sdf_faces, self.sample_target, h,
                                o.warped_band_cells * h,
                                terms=self._with_terms(ZeroEnergy(self.X0.shape[0])),
                                sign=o.source_sign, samples=o.occupancy_samples,
                                sample_weight=None if self.confidence is None else self.confidence.sample)
        field_starts = [(label, np.zeros((1, 3, 4)) if T0 is None else T0) for label, T0, _ in starts]
        skipped, placed = [], [self.basis.deform(T) for _, T in field_starts]
        for label, T0 in candidates:  # other orientations; one that repeats a start is skipped
            X = self.basis.deform(T0)
            if any(_rms(X - P) < o.start_merge_distance for P in placed):
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
                made = self._descriptor_field(field, made)
        return _WarpedFields(field, skipped, first, pruned, results, K, staged, made)

    def _warped_pass(self, starts, forward: "_StartRun", progress, candidates=(),
                     fields: "_WarpedFields | None" = None):
        """``warped_pass`` (docs/method.md, "The warped rest field"): minimize the warped rest
        field (:class:`~morphmodes_vol.warped_field.WarpedRestField`) from every start (and
        from ``candidates``, ``(label, T0)`` pairs: the initialization stage's other
        orientations with ``warped_candidates``; past ``warped_prune_modes`` modes only from
        those of field energy within ``warped_prune_ratio`` of the lowest), refine the field
        result of lowest objective
        and/or of lowest field energy (``warped_choice``) on Eq. (3) (one stage with all
        modes), and compare with the ``forward`` run's result by the objective on the full
        grid (``objectives`` and ``kept_before_hops`` in the report); then hop from the kept
        result (``warped_hops``: the field minimized from it with all modes, refined on
        Eq. 3, kept when its objective is below ``warped_hop_ratio`` times; ``hops`` in the
        report), and with ``warped_descriptors`` one more hop through the field with the heat
        kernel signatures as channels (``"field": "descriptors"`` in ``hops``). Returns the
        field, the refining runs, the report (``metrics["warped_pass"]``) and the seconds
        spent on the field (building it and minimizing it). ``fields``: the field runs made
        beside Algorithm 1's (:meth:`_warped_fields`, ``overlap_field``), else made here."""
        o = self.options
        if fields is None:
            fields = self._warped_fields(starts, candidates)
        field, skipped, first, pruned, results = (fields.field, fields.skipped, fields.first, fields.pruned,
                                                  fields.results)
        K, staged = fields.prune_modes, fields.staged
        objectives = {}  # on Eq. (3): source queries, so here rather than in _warped_fields
        for label, run in results.items():
            if o.warped_choice != "field":
                objectives[label] = self._objective(self.basis.deform(run.T))
            log.info("warped rest field from the %s start: %d evaluations, %d steps, %.2f s, "
                     "field energy %.4g%s", label, run.evaluations, run.steps, run.seconds, run.energy,
                     f", objective {objectives[label]:.4g}" if label in objectives else "")
        energies = {label: r.energy for label, r in results.items()}
        rankings = ([objectives] if o.warped_choice != "field" else []) + \
                   ([energies] if o.warped_choice != "objective" else [])
        start_labels = [label for label, _, _ in starts]
        chosen = []  # the lowest warped_refine by each ranking, in that order, once each
        for values in rankings:
            chosen += _ascending(values)[:o.warped_refine]
            if chosen[-1] not in start_labels:  # a candidate first: the best start's too
                chosen += _ascending({k: values[k] for k in start_labels if k in values})[:1]
        chosen = list(dict.fromkeys(chosen))
        options = o.replace(initial_modes=o.modes, lm_final_iterations=o.warped_polish_iterations)
        # a refined result is judged by the objective on the full grid when something is
        # compared with it: the runs' result, another refined one, a hop (the hops below run
        # as planned here, unless the objective is not finite or the descriptors fail)
        descriptor_hop = o.warped_descriptors and self.Y is not None  # an SDF target has no surface
        judge = forward is not None or len(chosen) > 1 or o.warped_hops > 0 or descriptor_hop
        runs = [self._run_starts([(WARPED_PREFIX + label, results[label].T, options)], progress, judge=judge)[0]
                for label in chosen]
        ran = {} if forward is None else {forward.label: self._full_grid_objective(forward)}  # field_only: no runs
        compared = {**ran, **{r.label: r.energy for r in runs}}
        # the orientation prior, as the initialization's (init_switch): a result from another
        # orientation is kept only when its objective is below warped_candidate_ratio times
        # every result from the starts' (a shape with a symmetry ties across orientations)
        own = {**ran, **{r.label: r.energy for r, label in zip(runs, chosen) if label in start_labels}}
        other = {r.label: r.energy for r, label in zip(runs, chosen) if label not in start_labels}
        kept = _ascending(own)[0]  # the forward result first among ties; a NaN one last
        if other:
            best_other = _ascending(other)[0]
            bar = o.warped_candidate_ratio * own[kept]
            if np.isfinite(other[best_other]) and not other[best_other] >= bar:
                kept = best_other
        best = next((r for r in runs if r.label == kept), min(
            runs, key=lambda r: r.energy if np.isfinite(r.energy) else np.inf))
        log.info("warped rest field: objective %s: kept the %s result",
                 ", ".join(f"{k} {e:.4g}" for k, e in compared.items()), kept)
        # hops through the field's landscape from the kept result (warped_hops): the field's
        # minimum near it, refined on Eq. (3), kept when its objective is below warped_hop_ratio
        # times the kept one's
        before_hops, objective = kept, compared[kept]
        current = best if forward is None or kept != forward.label else forward  # the result of label kept
        hops, hop_fields, descriptors, descriptor_seconds = [], [], {}, 0.0
        chains = [("hop", field, o.warped_hops)]
        if o.warped_descriptors and not descriptor_hop:
            log.info("warped_descriptors: a target given as an SDF has no surface for descriptors")
            descriptors = {"skipped": "the target is an SDF, not a mesh"}
        elif descriptor_hop and np.isfinite(objective):
            # then one hop through the field with descriptors (docs/method.md, "Descriptors
            # in the warped field")
            try:
                made = fields.descriptors
                if isinstance(made, Exception):
                    raise made
                dfield, grid_nodes, descriptor_seconds = made or self._descriptor_field(field)
            except DESCRIPTOR_ERRORS as exc:
                log.warning("warped_descriptors: no heat kernel signature (%s); no descriptor hop", exc)
                descriptors = {"skipped": f"no heat kernel signature: {exc}"}
            else:
                descriptors = {"channels": int(dfield.d0.shape[1]), "grid_nodes": grid_nodes}
                chains.append(("descriptor hop", dfield, 1))
        for name, hop_field, count in chains:
            for i in range(count if np.isfinite(objective) else 0):
                moved = hop_field.minimize(current.result.T, o.modes, o.warped_hop_iterations, first_mode=o.modes)
                hop_fields.append(moved)
                run = self._run_starts([(f"{WARPED_PREFIX}{name} {i + 1}", moved.T, options)], progress)[0]
                runs.append(run)
                accepted = bool(run.energy < o.warped_hop_ratio * objective)
                hops.append({"start": run.label, "from": current.label, "field_energy": float(moved.energy),
                             "objective": float(run.energy), "accepted": accepted,
                             "field": "descriptors" if hop_field.d0 is not None else "plain"})
                log.info("%s from the %s result: field energy %.4g, objective %.4g against %.4g: %s", run.label,
                         current.label, moved.energy, run.energy, objective, "kept" if accepted else "not kept")
                if not accepted:
                    break
                current, objective = run, run.energy
        kept = current.label
        report = {"kept": kept, "kept_before_hops": before_hops, "objectives": compared,
                  "field_objectives": objectives,
                  "field_energies": energies, "refined_start": best.label[len(WARPED_PREFIX):],
                  "refined_starts": chosen, "skipped_candidates": skipped,
                  "pruned": pruned, "prune_modes": K if staged else None,
                  "field_energies_at_prune": {label: r.energy for label, r in first.items()} if staged else {},
                  "field_nodes": int(len(field.points)), "hops": hops, "descriptors": descriptors}
        spent = [*results.values(), *(first[label] for label in pruned), *hop_fields]  # every field run, whole
        report["field_evaluations"] = int(sum(r.evaluations for r in spent))
        seconds = float(field.build_seconds + sum(r.seconds for r in spent) + descriptor_seconds)
        return field, runs, report, seconds

    def _descriptor_channels(self) -> "_DescriptorChannels":
        """The descriptor channels of the warped field (``warped_descriptors``; docs/method.md,
        "Descriptors in the warped field"): the heat kernel signatures of the source and the
        target mesh, the target's on a grid of half the quadrature's nodes over its box. They
        depend on the two meshes alone: :meth:`run` makes them beside the initialization
        (``overlap_field``)."""
        o = self.options
        t = time.perf_counter()
        source = heat_kernel_signature(self.X0, self.source_sdf_faces, seed=o.seed)
        target = heat_kernel_signature(self.Y, self.target_sdf_faces, seed=o.seed)
        grid = Grid.covering(self.quadrature.origin, self.quadrature.upper, max(max(self.quadrature.shape) // 2, 2))
        values = surface_descriptor_grid(self.Y, self.target_sdf_faces, target, grid)
        return _DescriptorChannels(source, values, grid, time.perf_counter() - t)

    def _descriptor_channels_or_error(self) -> "_DescriptorChannels | Exception":
        """:meth:`_descriptor_channels`, or the error that stopped it (raised again where
        the descriptor hop is made, which logs it and goes without)."""
        try:
            return self._descriptor_channels()
        except DESCRIPTOR_ERRORS as exc:
            return exc

    def _descriptor_field(self, field: WarpedRestField,
                          channels: "_DescriptorChannels | None" = None) -> tuple[WarpedRestField, int, float]:
        """``field`` with the descriptor channels (``channels``, made by
        :meth:`_descriptor_channels` when not given). Returns the field, the node count of
        the target's descriptor grid and the seconds spent on both."""
        c = self._descriptor_channels() if channels is None else channels
        t = time.perf_counter()
        dfield = field.with_descriptors((c.source, lambda P: trilinear_sample(c.values, c.grid, P)),
                                        self.options.warped_descriptor_weight)
        seconds = c.seconds + time.perf_counter() - t
        log.info("descriptor field: heat kernel signatures and the target's grid of %d nodes (%.2f s)",
                 c.grid.size, seconds)
        return dfield, int(c.grid.size), seconds

    def _landmark_metrics(self, vertices: np.ndarray, target_diagonal: float) -> dict:
        """RMS landmark distance of the rest pose and of the registered ``vertices (n, 3)``,
        in the target's units and as a fraction of its bounding-box diagonal."""
        before = landmark_rms(self.source_vertices, self.landmarks)
        after = landmark_rms(vertices, self.landmarks)
        return {"landmarks": len(self.landmarks), "initial_landmark_rms": before,
                "landmark_rms": after, "landmark_rms_fraction": after / target_diagonal}


@dataclass(frozen=True)
class _DescriptorChannels:
    """What :meth:`Registration._descriptor_channels` makes: the source's heat kernel
    signatures ``source (n, c)``, the target's on the nodes of ``grid`` (``values``, as
    :func:`~morphmodes_vol.descriptors.surface_descriptor_grid` returns them) and the seconds
    spent."""

    source: np.ndarray
    values: np.ndarray
    grid: Grid
    seconds: float


@dataclass(frozen=True)
class _WarpedFields:
    """What :meth:`Registration._warped_fields` returns: the field, the candidates skipped,
    every field run to ``prune_modes`` modes (``first``), those stopped there (``pruned``,
    label -> field energy) and the finished runs (``results``); ``staged``: whether the runs
    were stopped at ``prune_modes`` at all; ``descriptors``: the descriptor field made beside
    them (``_descriptor_field``'s result or its error), else ``None``."""

    field: WarpedRestField
    skipped: list
    first: dict
    pruned: dict
    results: dict
    prune_modes: int
    staged: bool
    descriptors: tuple | Exception | None = None  # _descriptor_field's result, or its error


@dataclass
class _StartRun:
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


def _points_queried(energy) -> int:
    """Points an evaluator (:meth:`Registration.energy` or :meth:`coarse_energy`) sent to the
    source mesh's closest-point queries: at its evaluations and, on the band quadrature, at
    the block centres its refreshes asked."""
    return int(energy.points_queried + getattr(energy, "centres_queried", 0))


def _comparison_counters(evaluators) -> tuple[int, int, float]:
    """Evaluations, points queried and seconds of the comparison objectives' evaluators
    (:meth:`Registration._cached`), summed; ``run`` reports the difference it made."""
    evaluators = list(evaluators)
    return (sum(e.evaluations for e in evaluators), sum(_points_queried(e) for e in evaluators),
            sum(e.seconds for e in evaluators))


def _labelled(progress: Callable[[ProgressEvent], None], label: str) -> Callable[[ProgressEvent], None]:
    """``progress`` with the events' ``start`` set to ``label``."""
    return lambda event: progress(replace(event, start=label))


def _ascending(values: dict) -> list:
    """The keys of ``values`` by ascending value, NaN and infinite values last, ties in
    their order."""
    return sorted(values, key=lambda k: (not np.isfinite(values[k]), np.nan_to_num(values[k], nan=0.0)))


def _rms(D: np.ndarray) -> float:
    """RMS length of the rows of ``D (n, 3)``: the RMS distance between two placements of
    the vertices."""
    return float(np.sqrt(np.mean(np.sum(D**2, axis=1))))


def _select_start(runs: list[_StartRun], factor: float) -> _StartRun:
    """The least distorted run (lowest edge strain) among those whose objective is within
    ``factor`` of the lowest: the same body in another pose is close to an isometry, and a
    registration with wrong correspondences may fit the SDF as well but stretch the surface
    more (docs/method.md)."""
    finite = [r for r in runs if np.isfinite(r.energy)]
    if not finite:
        return runs[0]
    lowest = min(r.energy for r in finite)
    return min((r for r in finite if r.energy <= factor * lowest), key=lambda r: r.strain)


def scan_target(target, options: RegistrationOptions | None = None):
    """A point-cloud target (a file of :data:`~morphmodes_vol.pointcloud.POINT_EXTENSIONS`
    without faces, or a :class:`~morphmodes_vol.pointcloud.PointCloud`) as what the
    registration takes (``options.point_sdf``): its SDF on a grid over its padded box, in its
    own frame (``"winding"``), or its Poisson surface as a mesh ``(V, F)`` (``"poisson"``); any
    other target as it is.

    Raises
    ------
    PointCloudError
        A point cloud that cannot be read, fails :func:`~morphmodes_vol.pointcloud.as_point_cloud`
        or has no normals that can be estimated.
    """
    options = options or RegistrationOptions()
    if is_point_cloud_file(target):
        cloud = load_point_cloud(target)
    elif isinstance(target, PointCloud):
        cloud = as_point_cloud(target)
    else:
        return target
    t = time.perf_counter()
    normals = oriented_normals(cloud)
    if options.point_sdf == "poisson":
        V, F = poisson_surface(cloud.points, normals, poisson_depth(options.resolved_target_grid))
        log.info("target: Poisson surface of %d points, %d triangles (%.2f s)", len(cloud.points), len(F),
                 time.perf_counter() - t)
        return V, F
    P = cloud.points
    lo, hi = P.min(axis=0), P.max(axis=0)
    grid = Grid.covering(lo, hi, options.resolved_target_grid, options.padding * float(np.linalg.norm(hi - lo)))
    sdf = points_target_sdf(P, normals, grid, "winding")
    sdf.extrapolate = True  # a source beyond the scan's box: the distance to the box is added
    log.info("target: SDF of %d oriented points on %s nodes (%.2f s)", len(P), grid.shape, time.perf_counter() - t)
    return sdf


def _as_target_sdf(target, options: RegistrationOptions) -> TargetSDF | None:
    """The target as a loaded SDF, or ``None`` when it is a mesh."""
    if is_target_sdf_path(target):
        if options.target_backend != "dense":
            log.info("target %s is an SDF file: its type decides the backend", target)
        return load_target_sdf(target, sign=options.target_sign)
    if hasattr(target, "sample") and hasattr(target, "surface_bounds"):
        return target
    return None


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
