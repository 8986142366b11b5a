"""The registration pipeline: preprocessing -> eigenbasis -> optimize -> export-ready result.

:class:`Registration` holds the expensive state of one source/target pair (normalized
meshes, quadrature, target SDF, eigenbasis), built once; :func:`register` is the one-call
function.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .eigenbasis import LBSBasis, mesh_skinning_weights, to_paper_z
from .energy import SDFEnergy
from .errors import OptionError
from .mesh import MeshLike, Normalization, as_mesh, bbox_diagonal, joint_normalization
from .metrics import ground_truth_error, shape_metrics
from .options import RegistrationOptions
from .optimize import OptimizationHistory, ProgressEvent, optimize_adaptive
from .sdf import DenseTargetSDF, Grid, closest_points

__all__ = ["register", "Registration", "RegistrationResult", "ground_truth_error"]

log = logging.getLogger(__name__)


def _is_closed(F: np.ndarray) -> bool:
    """Every undirected edge is shared by exactly two triangles."""
    edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool(np.all(counts == 2))


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
        ``converged``, ``stage_cap`` or ``max_iterations``.
    timings : dict of str to float
        Seconds per stage: ``preprocess``, ``target_sdf``, ``eigenbasis``, ``optimize``,
        ``correspondence``.
    metrics : dict of str to float
        Energies, RMS SDF residuals, surface distance and degeneracy
        (:func:`morphmodes_vol.metrics.shape_metrics`), and ground-truth errors when a ground
        truth was given.
    correspondence_faces : (n,) int64
        For every registered vertex, the closest target face.
    correspondence_barycentrics : (n, 3) float64
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
    correspondence_faces: np.ndarray
    correspondence_barycentrics: np.ndarray
    normalization: Normalization
    options: RegistrationOptions
    target_vertices: np.ndarray = field(repr=False, default=None)
    target_faces: np.ndarray = field(repr=False, default=None)

    @property
    def evaluations(self) -> int:
        """Number of full source-SDF evaluations."""
        return self.history.evaluations

    @property
    def modes(self) -> int:
        """Number of modes active at the end."""
        return int(self.T.shape[0])


class Registration:
    """State of one registration, built once: normalized meshes, grids, eigenbasis (first, so
    a source it cannot use fails early), target SDF.

    Parameters
    ----------
    source, target : path, trimesh.Trimesh or (V, F) tuple
    options : RegistrationOptions, optional

    Examples
    --------
    >>> from morphmodes_vol.primitives import capsule
    >>> V, F = capsule(count=(8, 8))
    >>> reg = Registration((V, F), (V * [1.1, 1, 1], F), RegistrationOptions(grid=16, modes=2))
    >>> result = reg.run()
    >>> result.vertices.shape == V.shape
    True
    """

    def __init__(self, source: MeshLike, target: MeshLike, options: RegistrationOptions | None = None):
        self.options = options if options is not None else RegistrationOptions()
        self.timings: dict[str, float] = {}

        t = time.perf_counter()
        # 4 vertices: the least that determines the affine map of the first mode
        self.source_vertices, self.source_faces = as_mesh(source, "source", min_vertices=4)
        self.target_vertices, self.target_faces = as_mesh(target, "target", min_vertices=3)
        if self.options.modes > self.source_vertices.shape[0]:
            raise OptionError(
                f"modes={self.options.modes} exceeds the source's "
                f"{self.source_vertices.shape[0]} vertices"
            )
        if self.options.source_sign == "raycast" and not _is_closed(self.source_faces):
            log.warning(
                "the source mesh is not closed (some edge is not shared by exactly two "
                "triangles): ray-parity signs may be wrong behind its holes; consider "
                "source_sign='winding'"
            )
        self.normalization = joint_normalization(self.source_vertices, self.target_vertices)
        self.X0 = self.normalization.apply(self.source_vertices)
        self.Y = self.normalization.apply(self.target_vertices)
        lo = np.minimum(self.X0.min(axis=0), self.Y.min(axis=0))
        hi = np.maximum(self.X0.max(axis=0), self.Y.max(axis=0))
        pad = self.options.padding * float(np.linalg.norm(hi - lo))
        self.quadrature = Grid.covering(lo, hi, self.options.grid, pad)
        self.target_grid = Grid.covering(lo, hi, self.options.resolved_target_grid, pad)
        self.timings["preprocess"] = time.perf_counter() - t

        t = time.perf_counter()
        self.weights, self.eigenvalues = mesh_skinning_weights(
            self.X0, self.source_faces, self.options.modes, seed=self.options.seed
        )
        self.basis = LBSBasis(self.X0, self.weights)
        self.timings["eigenbasis"] = time.perf_counter() - t
        log.info("%d skinning eigenmodes in %.2fs", self.options.modes, self.timings["eigenbasis"])

        t = time.perf_counter()
        self.target_sdf = DenseTargetSDF.from_mesh(self.Y, self.target_faces, self.target_grid)
        self.Q = self.quadrature.points()
        self.g = self.target_sdf.sample(self.Q)
        self.timings["target_sdf"] = time.perf_counter() - t
        log.info("target SDF on %s nodes, %d quadrature points, %.2fs",
                 self.target_grid.shape, self.Q.shape[0], self.timings["target_sdf"])

    def energy(self) -> SDFEnergy:
        """A fresh Eq. (3) evaluator for this pair (its evaluation counter starts at 0)."""
        return SDFEnergy(
            self.source_faces,
            self.Q,
            self.g,
            self.quadrature.cell_volume,
            sign=self.options.source_sign,
            samples=self.options.occupancy_samples,
        )

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
        t = time.perf_counter()
        energy = self.energy()
        out = optimize_adaptive(energy, self.basis, self.options, progress)
        timings["optimize"] = time.perf_counter() - t
        timings["sdf_queries"] = energy.seconds

        vertices = self.normalization.undo(out.vertices)

        t = time.perf_counter()
        # in the normalized frame (Open3D searches in float32); barycentrics and face ids
        # are invariant under the similarity, distances scale by 1 / normalization.scale
        cp = closest_points(self.Y, self.target_faces, out.vertices)
        timings["correspondence"] = time.perf_counter() - t

        metrics = {
            "initial_energy": float(out.initial.energy),
            "final_energy": float(out.final.energy),
            "initial_sdf_rms": out.initial.rms_residual,
            "final_sdf_rms": out.final.rms_residual,
            "sdf_rms_units": "fraction of the union bounding-box diagonal",
            "mean_distance_to_target": float(cp.distance.mean() / bbox_diagonal(self.Y)),
        }
        if metrics["final_sdf_rms"] > 0.5 * metrics["initial_sdf_rms"]:
            log.warning(
                "the SDF residual fell only from %.3g to %.3g: the registration may have "
                "failed (source and target far apart or very differently oriented?)",
                metrics["initial_sdf_rms"], metrics["final_sdf_rms"],
            )
        if ground_truth is not None:
            truth = ground_truth if isinstance(ground_truth, np.ndarray) else as_mesh(ground_truth, "ground truth")[0]
            metrics["identity_error"] = ground_truth_error(self.source_vertices, truth)
            metrics["ground_truth_error"] = ground_truth_error(vertices, truth)
        # surface distance and degeneracy (morphmodes_vol.metrics)
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
            correspondence_faces=cp.faces,
            correspondence_barycentrics=cp.barycentrics,
            normalization=self.normalization,
            options=self.options,
            target_vertices=self.target_vertices,
            target_faces=self.target_faces,
        )


def register(
    source: MeshLike,
    target: MeshLike,
    options: RegistrationOptions | None = None,
    *,
    progress: Callable[[ProgressEvent], None] | None = None,
    ground_truth: MeshLike | np.ndarray | None = None,
    **option_overrides,
) -> RegistrationResult:
    """Register ``source`` onto ``target`` by SDF matching in an adaptive skinning-eigenmode
    subspace (MorphModes, Algorithm 1).

    Parameters
    ----------
    source, target : path, trimesh.Trimesh or (V, F) tuple
        Triangle meshes. The source's vertex order is kept.
    options : RegistrationOptions, optional
        All tunables; keyword overrides (``grid=48, modes=10``) are applied on top.
    progress : callable, optional
        Receives a :class:`~morphmodes_vol.optimize.ProgressEvent` after every step.
    ground_truth : optional
        Target positions of the source vertices (same order), for error metrics.

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
    return Registration(source, target, options).run(progress=progress, ground_truth=ground_truth)
