"""ICP baselines: rigid ICP (trimesh's ``registration.icp`` iteration, closest points from
Open3D: :func:`morphmodes_vol.initialize.icp_align`) and non-rigid ICP (Amberg et al. 2007,
trimesh's ``registration.nricp_amberg``).

They run in the pair's normalized frame (joint unit-diagonal box, see
:mod:`morphmodes_vol.mesh`), so ``threshold`` is in those units; trimesh's
``nricp_amberg`` normalizes again by the source's own scale, and its
``distance_threshold`` is relative to that.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from ..mesh import MeshLike
from ..options import RegistrationOptions
from .result import BaselineResult, PreparedPair, finish, prepare_pair

__all__ = ["rigid_icp", "nricp", "nricp_onto_points", "NRICP_STEPS"]

log = logging.getLogger(__name__)

NRICP_STEPS = (
    (0.01, 10.0, 0.5, 10),
    (0.02, 5.0, 0.5, 10),
    (0.03, 2.5, 0.5, 10),
    (0.01, 0.0, 0.0, 10),
)
"""trimesh's default schedule of ``nricp_amberg``: ``(ws, wl, wn, max_iter)`` per step,
stiffness ``ws`` (Amberg's alpha), landmark weight ``wl`` (unused without landmarks), normal
weighting ``wn``, iterations."""


def _pair(source, target, pair, options):
    return pair if pair is not None else prepare_pair(source, target, options)


def _icp_matrix(X: np.ndarray, pair: PreparedPair, max_iterations: int, threshold: float) -> tuple[np.ndarray, float]:
    """The ``(4, 4)`` rigid map of :func:`morphmodes_vol.initialize.icp_align` (the iteration
    of trimesh's ``registration.icp``) and its final cost."""
    from ..initialize import icp_align

    r = icp_align(X, pair.Y, pair.target_faces, scale=False, max_iterations=max_iterations,
                  threshold=threshold)
    return np.vstack([r.matrix, [0.0, 0.0, 0.0, 1.0]]), r.cost


def rigid_icp(
    source: MeshLike,
    target: MeshLike,
    *,
    max_iterations: int = 100,
    threshold: float = 1e-10,
    ground_truth=None,
    options: RegistrationOptions | None = None,
    pair: PreparedPair | None = None,
) -> BaselineResult:
    """Rigid ICP (rotation and translation, no reflection, no scale) of the source vertices
    onto the target surface, started at the identity: trimesh ``registration.icp``'s iteration
    with Open3D's closest points on the triangles (:func:`morphmodes_vol.initialize.icp_align`,
    the same matrix about 40 times faster).

    Parameters
    ----------
    source, target : path, trimesh.Trimesh or (V, F) tuple
    max_iterations : int
    threshold : float
        Stop when the cost (mean squared distance, normalized units squared) decreases by
        less. trimesh's default 1e-5 stops after a step or two at unit scale.
    ground_truth : optional
        Where each source vertex belongs, for error metrics.
    options : RegistrationOptions, optional
        Only ``grid`` and ``padding`` matter (the quadrature of the SDF residual metric).
    pair : PreparedPair, optional
        Reuse a prepared pair (:func:`prepare_pair`) instead of ``source``/``target``.

    Returns
    -------
    BaselineResult
        ``info["matrix"]``: the (4, 4) rigid map in the normalized frame.

    Examples
    --------
    >>> from morphmodes_vol.primitives import capsule
    >>> V, F = capsule(count=(8, 8))
    >>> r = rigid_icp((V, F), (V + [0.02, 0, 0], F), options=RegistrationOptions(grid=8))
    >>> r.vertices.shape, r.method
    ((66, 3), 'ricp')
    """
    t = time.perf_counter()
    pair = _pair(source, target, pair, options)
    timings = {"preprocess": time.perf_counter() - t}
    t = time.perf_counter()
    matrix, cost = _icp_matrix(pair.X0, pair, max_iterations, threshold)
    X = pair.X0 @ matrix[:3, :3].T + matrix[:3, 3]
    timings["optimize"] = time.perf_counter() - t
    return finish("ricp", pair, pair.normalization.undo(X), "converged", timings, ground_truth,
                  {"matrix": matrix, "cost": cost})


def nricp(
    source: MeshLike,
    target: MeshLike,
    *,
    rigid_first: bool = False,
    steps=NRICP_STEPS,
    distance_threshold: float = 0.1,
    eps: float = 1e-4,
    gamma: float = 1.0,
    icp_iterations: int = 100,
    ground_truth=None,
    options: RegistrationOptions | None = None,
    pair: PreparedPair | None = None,
) -> BaselineResult:
    """Non-rigid ICP (Amberg et al. 2007, "Optimal Step Nonrigid ICP Algorithms for Surface
    Registration"; trimesh ``registration.nricp_amberg``), optionally after rigid ICP.

    Parameters
    ----------
    source, target : path, trimesh.Trimesh or (V, F) tuple
    rigid_first : bool
        Run :func:`rigid_icp` first and start NRICP from its result (the paper's
        RICP+NRICP).
    steps : sequence of (ws, wl, wn, max_iter)
        NRICP schedule (default trimesh's, :data:`NRICP_STEPS`).
    distance_threshold : float
        Closest-point matches farther than this are ignored, relative to the source's
        scale (trimesh normalizes by it).
    eps, gamma : float
        trimesh's step-end tolerance and translation weight.
    icp_iterations : int
        Iterations of the rigid stage.
    ground_truth, options, pair
        As for :func:`rigid_icp`.

    Returns
    -------
    BaselineResult
        ``method`` is ``"nricp"`` or ``"ricp+nricp"``.
    """
    import trimesh
    from trimesh.registration import nricp_amberg

    t = time.perf_counter()
    pair = _pair(source, target, pair, options)
    timings = {"preprocess": time.perf_counter() - t}
    X = pair.X0
    info: dict = {}
    if rigid_first:
        t = time.perf_counter()
        matrix, cost = _icp_matrix(X, pair, icp_iterations, 1e-10)
        X = X @ matrix[:3, :3].T + matrix[:3, 3]
        timings["rigid"] = time.perf_counter() - t
        info.update(matrix=matrix, cost=cost)
    t = time.perf_counter()
    X = nricp_amberg(
        trimesh.Trimesh(X, pair.source_faces, process=False),
        trimesh.Trimesh(pair.Y, pair.target_faces, process=False),
        steps=[list(s) for s in steps],
        eps=eps,
        gamma=gamma,
        distance_threshold=distance_threshold,
    )
    timings["optimize"] = time.perf_counter() - t
    method = "ricp+nricp" if rigid_first else "nricp"
    return finish(method, pair, pair.normalization.undo(np.asarray(X)), "converged", timings,
                  ground_truth, info)


def nricp_onto_points(source: MeshLike, points: np.ndarray, *, rigid_first: bool = True, steps=NRICP_STEPS,
                      distance_threshold: float = 0.1, eps: float = 1e-4, gamma: float = 1.0,
                      icp_iterations: int = 100) -> np.ndarray:
    """RICP+NRICP onto a point cloud (a scan): rigid ICP of the source vertices onto their
    nearest points (a KD-tree, ``trimesh.registration.procrustes``), then trimesh's
    ``nricp_amberg`` with the points as its target (closest points, no faces), both in the
    joint normalized frame.

    Parameters
    ----------
    source : path, trimesh.Trimesh or (V, F) tuple
    points : (k, 3) float
        The target points, in the source's frame.

    Returns
    -------
    (n, 3) float
        The registered source vertices, in the source's original frame.

    Examples
    --------
    >>> from morphmodes_vol.primitives import icosphere
    >>> V, F = icosphere(2)
    >>> X = nricp_onto_points((V, F), V * 1.1 + [0.05, 0, 0])
    >>> bool(np.abs(np.linalg.norm(X - [0.05, 0, 0], axis=1) - 1.1).max() < 0.05)
    True
    """
    import trimesh
    from scipy.spatial import cKDTree
    from trimesh.registration import nricp_amberg, procrustes

    from ..mesh import as_mesh, joint_normalization

    V, F = as_mesh(source, "source", min_vertices=4)
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) < 3 or not np.isfinite(P).all():
        raise ValueError(f"points must be finite (k, 3) with k >= 3, got shape {P.shape}")
    n = joint_normalization(V, P)
    X, Y = n.apply(V), n.apply(P)
    if rigid_first:
        tree, old = cKDTree(Y), np.inf
        for _ in range(icp_iterations):
            _, j = tree.query(X)
            _, X, cost = procrustes(X, Y[j], reflection=False, translation=True, scale=False, return_cost=True)
            if not old - cost > 1e-10:
                break
            old = cost
    X = nricp_amberg(trimesh.Trimesh(X, F, process=False), Y, steps=[list(s) for s in steps], eps=eps,
                     gamma=gamma, distance_threshold=distance_threshold, use_faces=False)
    return n.undo(np.asarray(X, dtype=np.float64))
