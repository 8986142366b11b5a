"""What every baseline returns, and the shared set-up and metrics."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..mesh import MeshLike, as_mesh
from ..metrics import ground_truth_error, sdf_residual, shape_metrics
from ..options import RegistrationOptions
from ..register import Registration

__all__ = ["BaselineResult", "PreparedPair", "prepare_pair", "pair_metrics"]

PreparedPair = Registration
"""A prepared source/target pair: joint normalization, quadrature and target SDF (and a
1-mode eigenbasis); a :class:`~morphmodes_vol.Registration` built with ``modes=1``."""


@dataclass
class BaselineResult:
    """Output of a baseline, with the conventions of
    :class:`~morphmodes_vol.RegistrationResult`.

    Attributes
    ----------
    method : str
        Short name (``"ricp"``, ``"nricp"``, ``"ricp+nricp"``, ``"full"``, ...).
    vertices : (n, 3) float64
        Registered source vertices, source's original frame and vertex order.
    faces : (f, 3) int64
        Source faces, unchanged.
    status : str
        ``converged`` or why the method stopped (``max_iterations``, ...).
    timings : dict of str to float
        Seconds per stage (``preprocess``, ``optimize``, ``metrics``).
    metrics : dict of str to float
        ``final_sdf_rms`` (normalized units), :func:`~morphmodes_vol.metrics.shape_metrics`
        and, with a ground truth, ``identity_error`` and ``ground_truth_error``.
    info : dict
        Method-specific details (iterations, evaluations, the rigid transform, ...).
    """

    method: str
    vertices: np.ndarray
    faces: np.ndarray
    status: str
    timings: dict
    metrics: dict
    info: dict = field(default_factory=dict)


def prepare_pair(source: MeshLike, target: MeshLike, options: RegistrationOptions | None = None) -> PreparedPair:
    """Normalize, build the quadrature and the target SDF once (``options.grid``), for the
    SDF-based baselines and for the SDF residual of every method."""
    options = options if options is not None else RegistrationOptions()
    return Registration(source, target, options.replace(modes=1, initial_modes=1))


def pair_metrics(pair: PreparedPair, vertices: np.ndarray, ground_truth=None) -> dict:
    """Metrics of registered ``vertices (n, 3)`` (source's original frame) of ``pair``:
    ``final_sdf_rms`` on the pair's quadrature, surface distance and degeneracy
    (:func:`~morphmodes_vol.metrics.shape_metrics`) and, with ``ground_truth`` (array, mesh
    or path), ``identity_error`` and ``ground_truth_error``."""
    X = pair.normalization.apply(vertices)
    truth = None
    metrics = {
        "final_sdf_rms": sdf_residual(X, pair.source_faces, pair.Q, pair.g, sign=pair.options.source_sign),
        "sdf_rms_units": "fraction of the union bounding-box diagonal",
    }
    if ground_truth is not None:
        truth = ground_truth if isinstance(ground_truth, np.ndarray) else as_mesh(ground_truth, "ground truth")[0]
        metrics["identity_error"] = ground_truth_error(pair.source_vertices, truth)
        truth = pair.normalization.apply(truth)
    metrics.update(shape_metrics(pair.X0, X, pair.source_faces, pair.Y, pair.target_faces, truth))
    return metrics


def finish(method: str, pair: PreparedPair, vertices: np.ndarray, status: str, timings: dict,
           ground_truth=None, info: dict | None = None) -> BaselineResult:
    """Assemble a :class:`BaselineResult`, computing its metrics."""
    t = time.perf_counter()
    metrics = pair_metrics(pair, vertices, ground_truth)
    timings = dict(timings, metrics=time.perf_counter() - t)
    return BaselineResult(method=method, vertices=np.asarray(vertices, dtype=np.float64),
                          faces=pair.source_faces.copy(), status=status, timings=timings,
                          metrics=metrics, info=dict(info or {}))
