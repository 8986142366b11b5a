"""Initialization without landmarks: a rigid or similarity alignment that minimizes the
same SDF energy, Eq. (3), started from several candidate orientations.

The paper starts Algorithm 1 at the rest pose, and its first stage (one mode: a global
affine map) is a local descent: on a body turned a lot as a whole it lands in a wrong basin
that later modes never leave. Here, before Algorithm 1:

1. *Candidates.* Each candidate maps the source's volume centroid onto the target's and
   turns it by one rotation of a fixed set: the 24 rotations of the cube (axis permutations
   with signs, determinant +1) and the four proper alignments of the source's principal axes
   with the target's. Centroids and principal axes are moments of the *volumes* (the
   quadrature nodes inside each shape on a coarse grid), so a differently sampled or
   partial surface does not bias them.
2. *Source field.* The source only moves rigidly (or by a similarity) here, so its signed
   distance is sampled once, by one closest-point query, on a grid of the coarse spacing
   in its rest frame (:class:`RigidSourceField`); Eq. (3) for any map ``x -> s R x + t``
   is then ``f(q) = s f_0(R^T (q - t) / s)``, trilinear in the samples: no mesh query per
   evaluation.
3. *Screening.* Eq. (3) on a coarse grid (``init_grid`` nodes along the longest side) at
   every candidate and at the rest pose; the unrotated start (centroids matched) and the
   ``init_candidates - 1`` lowest others go on.
4. *Refinement.* Each of those is refined by Levenberg-Marquardt on Eq. (3) restricted to
   rigid motions (6 parameters) or similarities (7): the residual's Jacobian with respect
   to a small rotation ``w``, translation ``t`` and log-scale ``s`` about the current
   centroid (``dx = [w]_x (x - c) + s (x - c) + t``) comes from the field's gradient; the
   damping is measured by the vertices' mean squared displacement; a step is applied
   exactly (Rodrigues rotation, ``exp(s)`` scale) and kept when the true energy decreases.
5. *Choice.* The refined start of lowest energy, unless its surface lies where the
   unrotated start's does (every vertex within one coarse spacing of it: a symmetry of the shape,
   whose energies tie only up to the grid's sampling, or the same pose reached from another
   orientation); then the unrotated one, whose vertex map does not turn the shape. When the
   chosen start is a rotated one, the unrotated one goes on beside it
   (:meth:`InitialAlignment.start_indices`): the rigid energy does not tell an articulated
   body's orientation, Algorithm 1's runs compare the two. The other refined starts
   that place the surface where a start does, with another vertex map (a symmetry), are
   its ``repeats``; the rest are the warped pass's candidates
   (:meth:`InitialAlignment.candidate_indices`). The
   chosen map ``x -> A [x; 1]`` is handed to Algorithm 1 as the coefficients of mode 0 (the
   constant mode, so ``T_0 = (A - [I 0]) / w_0``), which then goes on with a full affine
   map and the deformation modes from there.

:func:`icp_align` fits the source's *vertices* to the target's *surface* (rigid ICP from
the rest pose): the rigid step of the RICP+NRICP baseline (:mod:`morphmodes_vol.baselines`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field as dataclass_field
from functools import partial
from itertools import permutations, product
from typing import Callable

import numpy as np

from .optimize.gauss_newton import NormalEquations, damping_factor, lm_solve
from .runs import ascending
from .sdf.grid import Grid, trilinear_sample
from .sdf.source import _scene, inside, signed_distance

__all__ = ["IcpAlignment", "InitialAlignment", "RigidSourceField", "align", "candidate_rotations", "icp_align",
           "rotation_angle"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class InitialAlignment:
    """Result of :func:`align`.

    Attributes
    ----------
    matrix : (3, 4) float64
        The chosen map ``x -> matrix @ [x, 1]`` (normalized frame): ``scale * R`` and the
        translation.
    scale : float
    energy : float
        Eq. (3) on the coarse grid after refinement.
    rest_energy : float
        Eq. (3) on the coarse grid at the rest pose (no alignment).
    candidates : int
        Starts screened: the rotations of :func:`candidate_rotations` about the centroids,
        then the rest pose.
    chosen : int
        Index of the winner among them.
    screened_energies : (candidates,) float64
    refined_energies : dict of int to float
        Refined energy of each candidate refined.
    evaluations : int
        Evaluations of Eq. (3) on the coarse grid spent (each samples the source field
        :class:`RigidSourceField`; none queries the mesh).
    seconds : float
    field_nodes : int
        Nodes of the source field (its one closest-point query).
    refined_matrices : dict of int to (3, 4) float64
        The map each refined candidate reached (keys as ``refined_energies``; the chosen one
        is ``matrix``).
    repeats : tuple of int
        The refined candidates, other than the starts, that place the source's surface where
        a start (:meth:`start_indices`) places it with another vertex map: a symmetry of the
        shape (:meth:`candidate_indices` leaves them out).
    """

    matrix: np.ndarray
    scale: float
    energy: float
    rest_energy: float
    candidates: int
    chosen: int
    screened_energies: np.ndarray
    refined_energies: dict
    evaluations: int
    seconds: float
    field_nodes: int = 0
    refined_matrices: dict = dataclass_field(default_factory=dict)
    repeats: tuple = ()

    @property
    def rotation(self) -> np.ndarray:
        """``(3, 3)`` rotation part."""
        return self.matrix[:, :3] / self.scale

    def apply(self, X: np.ndarray) -> np.ndarray:
        """``(n, 3)`` points mapped."""
        return X @ self.matrix[:, :3].T + self.matrix[:, 3]

    def start_indices(self) -> dict:
        """The refined starts Algorithm 1 starts from, label -> index: ``"aligned"`` (the
        chosen one) and, when that is a rotated start, ``"unrotated"`` (index 0). The coarse
        rigid energy does not tell an articulated body's orientation (a head-to-tail flip
        fits nearly as well), so both orientations go on, to the runs' choice
        (docs/decisions/0010-no-orientation-prior.md)."""
        starts = {"aligned": self.chosen}
        if self.chosen != 0 and 0 in self.refined_matrices:
            starts["unrotated"] = 0
        return starts

    def candidate_indices(self) -> list:
        """The refined candidates that are other orientations than the starts, in the order
        they were refined: neither a start nor one of its ``repeats``. The warped pass
        starts from them (``warped_candidates``); its lowest objective decides among all
        results."""
        taken = set(self.start_indices().values()) | set(self.repeats)
        return [i for i in self.refined_matrices if i not in taken]

    def summary(self) -> dict:
        """Plain numbers for reports."""
        return {
            "init_rotation_deg": rotation_angle(self.rotation),
            "init_scale": float(self.scale),
            "init_translation": float(np.linalg.norm(self.matrix[:, 3])),
            "init_energy": float(self.energy),
            "init_rest_energy": float(self.rest_energy),
            "init_candidates": int(self.candidates),
            "init_evaluations": int(self.evaluations),
            "init_field_nodes": int(self.field_nodes),
        }


@dataclass(frozen=True)
class IcpAlignment:
    """Result of :func:`icp_align`.

    Attributes
    ----------
    matrix : (3, 4) float64
        The map ``x -> matrix @ [x, 1]`` (``scale * R`` and the translation).
    scale : float
    cost : float
        Mean squared distance of the mapped points to the surface at the last iteration.
    iterations : int
    seconds : float
    """

    matrix: np.ndarray
    scale: float
    cost: float
    iterations: int
    seconds: float

    def apply(self, X: np.ndarray) -> np.ndarray:
        """``(n, 3)`` points mapped."""
        return X @ self.matrix[:, :3].T + self.matrix[:, 3]

    def summary(self) -> dict:
        """Plain numbers for reports (no time: it is in the report's timings)."""
        return {
            "icp_rotation_deg": rotation_angle(self.matrix[:, :3] / self.scale),
            "icp_scale": float(self.scale),
            "icp_translation": float(np.linalg.norm(self.matrix[:, 3])),
            "icp_cost": float(self.cost),
            "icp_iterations": int(self.iterations),
        }


def icp_align(
    X: np.ndarray,
    V: np.ndarray,
    F: np.ndarray,
    *,
    scale: bool = False,
    max_iterations: int = 100,
    threshold: float = 1e-10,
) -> IcpAlignment:
    """Rigid (or similarity) ICP of the points ``X`` onto the surface ``(V, F)``, from the
    identity (Besl and McKay 1992).

    The iteration of ``trimesh.registration.icp``: the closest point of the surface to every
    mapped point, then the best rigid motion (``scale``: similarity) from the mapped points to
    those (``trimesh.registration.procrustes``), until the mean squared distance decreases by
    less than ``threshold``; the closest points come from one Open3D ``RaycastingScene``
    (float32), which on the 7k-vertex cat took 0.9 s for 100 iterations where trimesh's
    ``nearest.on_surface`` took 38 s to the same matrix.

    Parameters
    ----------
    X : (n, 3) float
        Points to align (the source vertices, normalized frame).
    V : (m, 3) float
    F : (f, 3) int
        Target surface, same frame.
    scale : bool
        Fit a uniform scale too.
    max_iterations : int
    threshold : float
        Stop when the cost decreases by less than this (or increases).

    Returns
    -------
    IcpAlignment

    Examples
    --------
    >>> from morphmodes_vol.primitives import icosphere
    >>> V, F = icosphere(2)
    >>> r = icp_align(V * [1.0, 0.8, 0.6], V * [1.0, 0.8, 0.6] + [0.05, 0.0, 0.0], F)
    >>> np.round(r.matrix, 3) + 0.0  # the translation found, no rotation
    array([[1.  , 0.  , 0.  , 0.05],
           [0.  , 1.  , 0.  , 0.  ],
           [0.  , 0.  , 1.  , 0.  ]])
    """
    from open3d.core import Tensor
    from trimesh.registration import procrustes

    t0 = time.perf_counter()
    a = np.array(X, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or len(a) < 3:
        raise ValueError(f"X must be (n, 3) with n >= 3, got {a.shape}")
    scene = _scene(V, F)
    total = np.eye(4)
    old_cost, cost, it = np.inf, np.inf, 0
    for it in range(1, max_iterations + 1):
        closest = scene.compute_closest_points(Tensor(np.ascontiguousarray(a, dtype=np.float32)))
        b = closest["points"].numpy().astype(np.float64)
        matrix, a, cost = procrustes(a, b, reflection=False, translation=True, scale=scale,
                                     return_cost=True)
        total = matrix @ total
        if old_cost - cost < threshold:
            break
        old_cost = cost
    s = float(np.cbrt(np.linalg.det(total[:3, :3])))
    return IcpAlignment(matrix=total[:3].copy(), scale=s, cost=float(cost), iterations=it,
                        seconds=time.perf_counter() - t0)


def rotation_angle(R: np.ndarray) -> float:
    """Angle in degrees of a ``(3, 3)`` rotation."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def _cube_rotations() -> np.ndarray:
    """The 24 proper rotations of the cube, ``(24, 3, 3)``; the identity first."""
    out = []
    for perm in permutations(range(3)):
        for signs in product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[np.arange(3), perm] = signs
            if np.linalg.det(R) > 0:
                out.append(R)
    out.sort(key=lambda R: -np.trace(R))  # identity (trace 3) first
    return np.array(out)


def _moments(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid ``(3,)`` and principal axes ``(3, 3)`` (columns, by decreasing variance)."""
    c = points.mean(axis=0)
    d = points - c
    evals, evecs = np.linalg.eigh(d.T @ d / max(len(points), 1))
    return c, evecs[:, ::-1]


def candidate_rotations(source_axes: np.ndarray | None = None, target_axes: np.ndarray | None = None) -> np.ndarray:
    """Candidate rotations ``(k, 3, 3)``: the 24 rotations of the cube (identity first), then,
    given both principal frames ``(3, 3)``, the four proper rotations taking the source's
    principal axes onto the target's (sign flips of the axes).

    Examples
    --------
    >>> R = candidate_rotations()
    >>> R.shape, bool(np.allclose(R[0], np.eye(3)))
    ((24, 3, 3), True)
    >>> bool(np.allclose(np.einsum('kij,kil->kjl', R, R), np.eye(3)))
    True
    """
    rots = list(_cube_rotations())
    if source_axes is not None and target_axes is not None:
        for signs in product((1.0, -1.0), repeat=3):
            R = target_axes @ np.diag(signs) @ source_axes.T
            if np.linalg.det(R) > 0:
                rots.append(R)
    return np.array(rots)


def _skew(w: np.ndarray) -> np.ndarray:
    """``[w]_x (3, 3)``: ``_skew(w) @ v == np.cross(w, v)``."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def rodrigues(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w (3,)``."""
    theta = float(np.linalg.norm(w))
    K = _skew(w)
    if theta < 1e-12:
        return np.eye(3) + K
    K /= theta
    return np.eye(3) + np.sin(theta) * K + (1.0 - np.cos(theta)) * (K @ K)


class Similarity:
    """``x -> scale * R @ x + t``."""

    def __init__(self, R: np.ndarray, t: np.ndarray, scale: float = 1.0):
        self.R, self.t, self.scale = R, t, scale

    def apply(self, X: np.ndarray) -> np.ndarray:
        return self.scale * X @ self.R.T + self.t

    def compose(self, w: np.ndarray, t: np.ndarray, s: float, c: np.ndarray) -> "Similarity":
        """This map followed by ``y -> exp(s) Rot(w) (y - c) + c + t``."""
        Rw, e = rodrigues(w), float(np.exp(s))
        return Similarity(Rw @ self.R, e * Rw @ (self.t - c) + c + t, e * self.scale)

    def matrix(self) -> np.ndarray:
        return np.hstack([self.scale * self.R, self.t[:, None]])


@dataclass(frozen=True)
class RigidSourceField:
    """The source's signed distance and its gradient sampled once on a grid of its own
    (rest) frame, so the alignment evaluates Eq. (3) for any similarity of the source by
    trilinear interpolation instead of a closest-point query per evaluation: a similarity
    ``x -> s R x + t`` moves the field to ``f(q) = s f_0(R^T (q - t) / s)`` exactly.

    Attributes
    ----------
    grid : Grid
        Nodes in the source's rest frame.
    values : (nx, ny, nz, 4) float64
        Signed distance (negative inside) and its gradient ``grad f_0`` at the nodes.
    queried : int or None
        Nodes sent to the closest-point query (``None``: all of them).
    """

    grid: Grid
    values: np.ndarray
    queried: int | None = None

    @classmethod
    def from_mesh(cls, X0: np.ndarray, F: np.ndarray, grid: Grid, sign: str = "raycast",
                  near: Callable[[np.ndarray], np.ndarray] | None = None) -> "RigidSourceField":
        """Sample the signed distance of ``(X0 (n, 3), F (f, 3))`` on ``grid``.

        With ``near`` (nodes ``(N, 3)`` -> ``(N,)`` bool, called once on the grid's nodes), only
        the nodes it keeps and the ones within a spacing of the source's bounding sphere are
        queried; the others, for points the caller never samples, get the distance to that
        sphere (a lower bound of the distance, positive there) and its gradient, so a stray
        sample still sees a field that grows outward.
        """
        P = grid.points()
        if near is None:
            sd = signed_distance(X0, F, P, sign=sign)
            values = np.concatenate([sd.value[:, None], sd.normal], axis=1)
            return cls(grid=grid, values=values.reshape(*grid.shape, 4))
        center = 0.5 * (X0.min(axis=0) + X0.max(axis=0))
        reach = float(np.linalg.norm(X0 - center, axis=1).max())
        offset = P - center
        dist = np.linalg.norm(offset, axis=1)
        near = np.asarray(near(P), dtype=bool) | (dist <= reach + grid.spacing)
        values = np.empty((P.shape[0], 4))
        sd = signed_distance(X0, F, P[near], sign=sign)
        values[near, 0], values[near, 1:] = sd.value, sd.normal
        far = ~near
        values[far, 0] = dist[far] - reach
        values[far, 1:] = offset[far] / dist[far, None]
        return cls(grid=grid, values=values.reshape(*grid.shape, 4), queried=int(near.sum()))

    @property
    def nodes(self) -> int:
        """Nodes sent to the closest-point query."""
        return self.grid.size if self.queried is None else self.queried

    def sample(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``f_0 (k,)`` and ``grad f_0 (k, 3)`` at points ``P (k, 3)`` of the rest frame.

        Outside the grid's box the value grows by the distance to the box (an upper bound of
        the true distance, continuous across the box) and the gradient is the boundary's.
        """
        out = trilinear_sample(self.values, self.grid, P)  # clamped to the box
        return out[:, 0] + self.grid.distance_outside(P), out[:, 1:]


@dataclass(frozen=True)
class _Evaluation:
    """Eq. (3) at one similarity: ``energy``, residual ``f - g (k,)``, moved field's value
    ``f (k,)`` and gradient ``normal (k, 3)`` at the quadrature points."""

    energy: float
    residual: np.ndarray
    value: np.ndarray
    normal: np.ndarray


def evaluate(field: RigidSourceField, S: "Similarity", Q: np.ndarray, g: np.ndarray,
              weight: np.ndarray) -> _Evaluation:
    """Eq. (3) for the source moved by ``S``: ``f(q) = s f_0(R^T (q - t) / s)``,
    ``grad f(q) = R grad f_0(...)``."""
    P = (Q - S.t) @ S.R / S.scale
    f0, n0 = field.sample(P)
    f = S.scale * f0
    r = f - g
    return _Evaluation(float((weight * r) @ r), r, f, n0 @ S.R.T)


def rigid_jacobian(ev: _Evaluation, Q: np.ndarray, c: np.ndarray, similarity: bool) -> np.ndarray:
    """``J (k, 6 or 7)``: derivative of the residual with respect to ``(w, t[, s])`` of the
    increment ``y -> exp(s) Rot(w) (y - c) + c + t`` applied after the current map.

    The moved field is ``f'(q) = exp(s) f(Rot(-w) (q - c - t) exp(-s) + c)``, so with
    ``a = q - c`` and ``n = grad f(q)``: ``df/dw = -(a x n)``, ``df/dt = -n`` and
    ``df/ds = f - n . a``.
    """
    a = Q - c
    n = ev.normal
    cols = [-np.cross(a, n), -n]
    if similarity:
        cols.append((ev.value - np.einsum("kd,kd->k", n, a))[:, None])
    return np.concatenate(cols, axis=1)


def motion_metric(X: np.ndarray, c: np.ndarray, similarity: bool) -> np.ndarray:
    """``M (6 or 7, 6 or 7)``: mean squared vertex displacement of an increment ``(w, t[, s])``
    about ``c``, ``p^T M p = mean_v |w x (x_v - c) + s (x_v - c) + t|^2`` (the damping's
    metric: steps are measured by how far they move the source)."""
    d = X - c
    k = 7 if similarity else 6
    G = np.zeros((X.shape[0], 3, k))
    for i, e in enumerate(np.eye(3)):
        G[:, :, i] = np.cross(e, d)  # the displacement of w = e_i: e_i x d
    G[:, :, 3:6] = np.eye(3)
    if similarity:
        G[:, :, 6] = d
    return np.einsum("vdi,vdj->ij", G, G) / X.shape[0]


def _refine(field: RigidSourceField, Q: np.ndarray, g: np.ndarray, weight: np.ndarray, X0: np.ndarray,
            start: Similarity, ev: _Evaluation, similarity: bool, iterations: int,
            damping: float = 1e-3) -> tuple[Similarity, _Evaluation, int]:
    """Levenberg-Marquardt on Eq. (3) over rigid motions or similarities, from ``start``.

    Returns the refined map, its evaluation and the number of field evaluations spent.
    """
    S, nu, spent = start, 2.0, 0
    for _ in range(iterations):
        X = S.apply(X0)
        c = X.mean(axis=0)
        J = rigid_jacobian(ev, Q, c, similarity)
        WJ = weight[:, None] * J
        model = NormalEquations(A=J.T @ WJ, g=WJ.T @ ev.residual)
        metric = motion_metric(X, c, similarity)
        accepted = False
        for _ in range(8):
            p = lm_solve(model, metric, damping)
            predicted = model.predicted_decrease(p)
            if not np.all(np.isfinite(p)) or not predicted > 0:
                break
            w, t, s = p[:3], p[3:6], (p[6] if similarity else 0.0)
            trial = S.compose(w, t, s, c)
            trial_ev = evaluate(field, trial, Q, g, weight)
            spent += 1
            rho = (ev.energy - trial_ev.energy) / predicted
            if np.isfinite(trial_ev.energy) and rho > 1e-4:
                damping *= damping_factor(rho)
                nu = 2.0
                decrease = ev.energy - trial_ev.energy
                S, ev, accepted = trial, trial_ev, True
                break
            damping *= nu
            nu *= 2.0
        if not accepted or decrease <= 1e-4 * ev.energy:
            break
    return S, ev, spent


FIELD_MAX_RESOLUTION = 160  # nodes per side: at most 4.1M nodes, 131 MB with the gradient


def source_field(X0: np.ndarray, F: np.ndarray, Q: np.ndarray, spacing: float, cs: np.ndarray,
                  ct: np.ndarray, scale: float, sign: str) -> RigidSourceField:
    """The source's field on a grid of the coarse spacing whose box holds every point the
    alignment samples: the quadrature box (the rest pose) and the ball about the source's
    centroid that a start about the centroids maps the quadrature points into, with a margin
    for the refinement's steps. Only the nodes within two spacings of that ball or of the
    quadrature box (the trilinear cells of points on their edges) are queried: the corners of
    the grid's box beyond both, about 40% of the nodes on the lion and the farthest from the
    source (the slowest queries), are never sampled (:meth:`RigidSourceField.from_mesh`)."""
    radius = 1.1 * float(np.linalg.norm(Q - ct, axis=1).max()) / scale + 2.0 * spacing
    lo = np.minimum(Q.min(axis=0), cs - radius)
    hi = np.maximum(Q.max(axis=0), cs + radius)
    resolution = int(np.ceil(float((hi - lo).max()) / spacing)) + 1
    if resolution > FIELD_MAX_RESOLUTION:  # a fine init_grid: bound the field's memory
        log.info("source field for the alignment: %d nodes per side capped at %d (spacing %.3g "
                 "instead of the coarse grid's %.3g)", resolution, FIELD_MAX_RESOLUTION,
                 float((hi - lo).max()) / (FIELD_MAX_RESOLUTION - 1), spacing)
        resolution = FIELD_MAX_RESOLUTION
    grid = Grid.covering(lo, hi, resolution)
    margin = 2.0 * spacing

    def near(P: np.ndarray) -> np.ndarray:
        return (np.linalg.norm(P - cs, axis=1) <= radius + margin) | np.all(
            (P >= Q.min(axis=0) - margin) & (P <= Q.max(axis=0) + margin), axis=1)

    return RigidSourceField.from_mesh(X0, F, grid, sign=sign, near=near)


def _volume_frames(X0, F, Q, g, kind: str, sign: str):
    """The volume centroids of source and target (from the coarse nodes inside each), the
    candidate rotations between their principal axes and, for a similarity, the scale of
    their volumes' ratio. An unsigned source (an open surface) has no inside: the nodes
    within a spacing of each surface stand in for it."""
    if sign == "unsigned":
        h = float(np.min(np.diff(np.unique(Q[:, 0]))))
        inside_t = Q[g < h]
        inside_s = Q[signed_distance(X0, F, Q, sign="unsigned").value < h]
    else:
        inside_t = Q[g < 0]
        inside_s = Q[inside(X0, F, Q, sign)]
    if len(inside_t) < 4 or len(inside_s) < 4:
        # a shape thinner than the coarse grid: fall back to its vertices' moments
        log.info("coarse initialization grid sees fewer than 4 nodes inside a shape; "
                 "using the source's vertices for its moments")
        inside_s = X0 if len(inside_s) < 4 else inside_s
        inside_t = inside_s if len(inside_t) < 4 else inside_t
    cs, axes_s = _moments(inside_s)
    ct, axes_t = _moments(inside_t)
    scale = 1.0
    if kind == "similarity" and len(inside_s) and len(inside_t):
        scale = float(np.clip((len(inside_t) / len(inside_s)) ** (1.0 / 3.0), 0.5, 2.0))
    return cs, ct, candidate_rotations(axes_s, axes_t), scale


def _refine_candidates(refine, order: list, starts: list, evaluations: list, progress):
    """Refine the starts ``order`` names (``refine(start, evaluation) -> (S, evaluation,
    evaluations spent)``); returns their refined energies and similarities by index and the
    evaluations spent."""
    refined, finals, spent = {}, {}, 0
    for rank_i, i in enumerate(order):
        S, ev, n = refine(starts[i], evaluations[i])
        spent += n
        refined[i], finals[i] = float(ev.energy), S
        if progress is not None:
            progress(f"candidate {rank_i + 1}/{len(order)}: rotation {rotation_angle(S.R):.0f} deg, "
                     f"energy {float(evaluations[i].energy):.3g} -> {ev.energy:.3g}")
    return refined, finals, spent


def _apart(field: RigidSourceField, X0: np.ndarray, S: "Similarity", T: "Similarity") -> float:
    """How far the source's vertices placed by ``S`` lie from its surface placed by ``T``:
    the largest distance (normalized frame). Below the coarse spacing, the two place the
    surface alike: a symmetry of the shape, or the same pose reached from two orientations."""
    P = (S.apply(X0) - T.t) @ T.R / T.scale  # S's vertices, in the rest frame of T
    return float(np.max(np.abs(field.sample(P)[0]))) * T.scale


def _chosen(order: list, refined: dict, finals: dict, field: RigidSourceField, X0: np.ndarray,
            spacing: float) -> int:
    """The refined start kept: the one of lowest energy, unless it places the source's
    surface where the unrotated start (``order[0]``) places it (:func:`_apart` below
    ``spacing``). Then the unrotated start is kept: its vertex map does not turn the
    shape, and a symmetric shape's energies tie only up to the grid's sampling."""
    best = ascending({i: refined[i] for i in order})[0]
    if best == order[0] or not np.isfinite(refined[best]):
        return order[0]
    apart = _apart(field, X0, finals[best], finals[order[0]])
    log.info("initial alignment: best start %d, energy %.4g (unrotated %.4g, ratio %.2f), its surface "
             "%.3g from the unrotated one's (%.3g: the same)", best, refined[best], refined[order[0]],
             refined[best] / max(refined[order[0]], 1e-300), apart, spacing)
    return order[0] if apart < spacing else best


def _repeats(order: list, starts: set, finals: dict, field: RigidSourceField, X0: np.ndarray,
             spacing: float) -> tuple:
    """The refined candidates of ``order``, other than ``starts``, that place the surface
    where one of ``starts`` does (:func:`_apart` below ``spacing``) with another vertex map
    (the vertices' root mean square distance above ``spacing``): a symmetry of the shape.
    One that places the vertices too where a start does is the same pose reached from
    another orientation; it is not a repeat and starts the warped pass as before."""
    def symmetric(S, T):
        moved = float(np.sqrt(np.mean(np.sum((S.apply(X0) - T.apply(X0)) ** 2, axis=1))))
        return moved > spacing and _apart(field, X0, S, T) < spacing
    return tuple(i for i in order if i not in starts and any(symmetric(finals[i], finals[j]) for j in starts))


def align(
    X0: np.ndarray,
    F: np.ndarray,
    Q: np.ndarray,
    g: np.ndarray,
    weight: float,
    *,
    kind: str = "similarity",
    keep: int = 4,
    iterations: int = 30,
    sign: str = "raycast",
    progress: Callable[[str], None] | None = None,
) -> InitialAlignment:
    """Multi-start rigid or similarity alignment of the source onto the target by Eq. (3).

    Parameters
    ----------
    X0 : (n, 3) float
        Source vertices (normalized frame).
    F : (f, 3) int
        Source triangles (as used for its SDF).
    Q : (k, 3) float
        Points of a coarse quadrature grid covering both shapes.
    g : (k,) float
        Target signed distance at ``Q`` (negative inside).
    weight : float or (k,) float
        Quadrature weight of every point (the coarse grid's cell volume, times an open
        target's confidence).
    kind : {"rigid", "similarity"}
    keep : int
        Candidates refined after screening.
    iterations : int
        Levenberg-Marquardt steps per refined candidate.
    sign : {"raycast", "winding", "unsigned"}
        Inside test of the source.
    progress : callable, optional
        Receives a short message per refined candidate.

    Returns
    -------
    InitialAlignment
    """
    if kind not in ("rigid", "similarity"):
        raise ValueError(f"kind={kind!r}: expected 'rigid' or 'similarity'")
    t0 = time.perf_counter()
    Q = np.ascontiguousarray(Q, dtype=np.float64)
    g = np.ascontiguousarray(g, dtype=np.float64)
    weights = np.broadcast_to(np.asarray(weight, dtype=np.float64), g.shape)
    if not np.max(weights) > 0:
        raise ValueError(f"weight must be positive (the coarse grid's cell volume), got {weight}")
    spacing = float(np.cbrt(float(np.max(weights))))  # the cell volume: the largest weight
    cs, ct, rotations, scale = _volume_frames(X0, F, Q, g, kind, sign)
    field = source_field(X0, F, Q, spacing, cs, ct, scale, sign)
    t_field = time.perf_counter() - t0

    # every rotation about the centroids (the identity first), and the rest pose itself (last)
    starts = [Similarity(R, ct - scale * R @ cs, scale) for R in rotations] + [Similarity(np.eye(3), np.zeros(3), 1.0)]
    evaluations = [evaluate(field, S, Q, g, weights) for S in starts]
    spent = len(starts)
    screened = np.array([ev.energy for ev in evaluations])
    rest = evaluations[-1]

    # the unrotated start is always refined and the best screened others join it (ascending
    # energy, NaN last, ties by index)
    order = [0] + sorted(range(1, len(starts)), key=lambda j: (
        bool(np.isnan(screened[j])), 0.0 if np.isnan(screened[j]) else float(screened[j]), j))[: max(0, keep - 1)]
    refine = partial(_refine, field, Q, g, weights, X0, similarity=kind == "similarity", iterations=iterations)
    refined, finals, n = _refine_candidates(refine, order, starts, evaluations, progress)
    spent += n
    best_i = _chosen(order, refined, finals, field, X0, spacing)
    best = finals[best_i]
    repeats = _repeats(order, {order[0], best_i}, finals, field, X0, spacing)
    result = InitialAlignment(
        matrix=best.matrix(), scale=float(best.scale), energy=refined[best_i],
        rest_energy=float(rest.energy), candidates=len(starts), chosen=best_i,
        screened_energies=screened, refined_energies=refined, evaluations=spent,
        seconds=time.perf_counter() - t0, field_nodes=field.nodes,
        refined_matrices={i: S.matrix() for i, S in finals.items()}, repeats=repeats,
    )
    log.info("initial alignment: candidate %d of %d, rotation %.1f deg, scale %.3f, coarse energy "
             "%.4g (rest pose %.4g), %d evaluations of the source field (%d nodes, %.2fs) in %.2fs",
             best_i, len(starts), rotation_angle(best.R), best.scale, refined[best_i], rest.energy,
             spent, field.nodes, t_field, result.seconds)
    return result
