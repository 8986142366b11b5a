"""Initialization without landmarks: a rigid or similarity alignment that minimizes the
same SDF energy, Eq. (3), started from several candidate orientations (issue 5).

The paper starts Algorithm 1 at the rest pose, and its first stage (one mode: a global
affine map) is a local descent: on a pose turned by 70-105 degrees (lion-04, -05, -07 of the
shared data) it lands in a wrong basin that later modes never leave. Here, before
Algorithm 1:

1. *Candidates.* Each candidate maps the source's volume centroid onto the target's and
   turns it by one rotation of a fixed set: the 24 rotations of the cube (axis permutations
   with signs, determinant +1) and the four proper alignments of the source's principal axes
   with the target's. Centroids and principal axes are moments of the *volumes* (the
   quadrature nodes inside each shape on a coarse grid), so a differently sampled or
   partial surface does not bias them.
2. *Screening.* Eq. (3) on a coarse grid (``init_grid`` nodes along the longest side) at
   every candidate and at the rest pose; the unrotated start (centroids matched) and the
   ``init_candidates - 1`` lowest others go on.
3. *Refinement.* Each of those is refined by Levenberg-Marquardt on Eq. (3) restricted to
   rigid motions (6 parameters) or similarities (7): the Gauss-Newton model of
   :mod:`morphmodes_vol.optimize.gauss_newton` for one constant mode (a global affine map)
   about the current pose, composed with the linear map from a small rotation ``w``,
   translation ``t`` and log-scale ``s`` to that affine increment
   (``dx = [w]_x (x - c) + s (x - c) + t``); a step is applied exactly (Rodrigues rotation,
   ``exp(s)`` scale) and kept when the true energy decreases.
4. *Choice, with an orientation prior.* The unrotated start's alignment is kept unless a
   rotated start reaches an energy below ``init_switch`` times its energy. On the
   articulated lion and cat poses the lowest rigid energy was a head-to-tail flip on 8 of
   18 pairs (and a 95-degree error on one more), at energy ratios 0.68-1.00 to the
   unrotated start; rotated starts that were right where the unrotated one was not won by
   ratios of 0.38-0.55 on three pairs and 0.72 on one, which the prior misses
   (docs/method.md). The
   chosen map ``x -> A [x; 1]`` is handed to Algorithm 1 as the coefficients of mode 0 (the
   constant mode, so ``T_0 = (A - [I 0]) / w_0``), which then goes on with a full affine
   map and the deformation modes from there.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from itertools import permutations, product
from typing import Callable

import numpy as np

from .eigenbasis.lbs import LBSBasis
from .energy import EnergyEvaluation, SDFEnergy
from .optimize.gauss_newton import lm_solve, subspace_metric, subspace_normal_equations

__all__ = ["InitialAlignment", "align", "candidate_rotations", "rotation_angle"]

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
        Coarse-grid SDF evaluations spent.
    seconds : float
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

    @property
    def rotation(self) -> np.ndarray:
        """``(3, 3)`` rotation part."""
        return self.matrix[:, :3] / self.scale

    def apply(self, X: np.ndarray) -> np.ndarray:
        """``(n, 3)`` points mapped."""
        return X @ self.matrix[:, :3].T + self.matrix[:, 3]

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
        }


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


def _rodrigues(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w (3,)``."""
    theta = float(np.linalg.norm(w))
    K = _skew(w)
    if theta < 1e-12:
        return np.eye(3) + K
    K /= theta
    return np.eye(3) + np.sin(theta) * K + (1.0 - np.cos(theta)) * (K @ K)


def _increment_map(c: np.ndarray, similarity: bool) -> np.ndarray:
    """``L (12, 6 or 7)``: parameters ``(w, t[, s])`` to the flattened affine increment ``T``
    (index ``4 a + b``) of ``dx = [w]_x (x - c) + s (x - c) + t``."""
    cols = []
    for k in range(7 if similarity else 6):
        p = np.zeros(7)
        p[k] = 1.0
        w, t, s = p[:3], p[3:6], p[6]
        Lin = _skew(w) + s * np.eye(3)
        T = np.hstack([Lin, (t - Lin @ c)[:, None]])
        cols.append(T.reshape(-1))
    return np.array(cols).T


class _Similarity:
    """``x -> scale * R @ x + t``."""

    def __init__(self, R: np.ndarray, t: np.ndarray, scale: float = 1.0):
        self.R, self.t, self.scale = R, t, scale

    def apply(self, X: np.ndarray) -> np.ndarray:
        return self.scale * X @ self.R.T + self.t

    def compose(self, w: np.ndarray, t: np.ndarray, s: float, c: np.ndarray) -> "_Similarity":
        """This map followed by ``y -> exp(s) Rot(w) (y - c) + c + t``."""
        Rw, e = _rodrigues(w), float(np.exp(s))
        return _Similarity(Rw @ self.R, e * Rw @ (self.t - c) + c + t, e * self.scale)

    def matrix(self) -> np.ndarray:
        return np.hstack([self.scale * self.R, self.t[:, None]])


def _refine(energy: SDFEnergy, X0: np.ndarray, start: _Similarity, ev: EnergyEvaluation,
            similarity: bool, iterations: int, damping: float = 1e-3) -> tuple[_Similarity, EnergyEvaluation]:
    """Levenberg-Marquardt on Eq. (3) over rigid motions or similarities, from ``start``."""
    S, nu = start, 2.0
    n = X0.shape[0]
    ones = np.ones((n, 1))
    for _ in range(iterations):
        X = S.apply(X0)
        c = X.mean(axis=0)
        basis = LBSBasis(X, ones)  # one constant mode: affine increments about the current pose
        model = subspace_normal_equations(ev, basis, 1, energy.F, energy.weights)
        L = _increment_map(c, similarity)
        metric = L.T @ subspace_metric(basis, 1) @ L
        reduced = type(model)(A=L.T @ model.A @ L, g=L.T @ model.g)
        accepted = False
        for _ in range(8):
            p = lm_solve(reduced, metric, damping)
            predicted = reduced.predicted_decrease(p)
            if not np.all(np.isfinite(p)) or not predicted > 0:
                break
            w, t, s = p[:3], p[3:6], (p[6] if similarity else 0.0)
            trial = S.compose(w, t, s, c)
            trial_ev = energy.evaluate(trial.apply(X0))
            rho = (ev.energy - trial_ev.energy) / predicted
            if np.isfinite(trial_ev.energy) and rho > 1e-4:
                damping *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                decrease = ev.energy - trial_ev.energy
                S, ev, accepted = trial, trial_ev, True
                break
            damping *= nu
            nu *= 2.0
        if not accepted or decrease <= 1e-4 * ev.energy:
            break
    return S, ev


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
    switch: float = 0.5,
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
    weight : float
        Quadrature weight of every point (the coarse grid's cell volume).
    kind : {"rigid", "similarity"}
    keep : int
        Candidates refined after screening.
    iterations : int
        Levenberg-Marquardt steps per refined candidate.
    switch : float
        A rotated start replaces the unrotated one only when its refined energy is below
        ``switch`` times the unrotated one's (``1``: plain lowest energy; ``0``: never).
    sign : {"raycast", "winding"}
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
    energy = SDFEnergy(F, Q, g, weight, sign=sign)
    rest = energy.evaluate(X0)
    inside_t = Q[g < 0]
    inside_s = Q[rest.residual + g < 0]  # f = r + g
    if len(inside_t) < 4 or len(inside_s) < 4:
        # a shape thinner than the coarse grid: fall back to its vertices' moments
        log.info("coarse initialization grid sees fewer than 4 nodes inside a shape; "
                 "using the source's vertices for its moments")
        inside_s = X0 if len(inside_s) < 4 else inside_s
        inside_t = inside_s if len(inside_t) < 4 else inside_t
    cs, axes_s = _moments(inside_s)
    ct, axes_t = _moments(inside_t)
    rotations = candidate_rotations(axes_s, axes_t)
    scale = 1.0
    if kind == "similarity" and len(inside_s) and len(inside_t):
        scale = float(np.clip((len(inside_t) / len(inside_s)) ** (1.0 / 3.0), 0.5, 2.0))

    # every rotation about the centroids (the identity first), and the rest pose itself (last)
    starts = [_Similarity(R, ct - scale * R @ cs, scale) for R in rotations]
    starts.append(_Similarity(np.eye(3), np.zeros(3), 1.0))
    screened = np.empty(len(starts))

    def rank(j: int) -> tuple:  # ascending energy, NaN last, ties by index (a stable sort)
        e = screened[j]
        return (bool(np.isnan(e)), 0.0 if np.isnan(e) else float(e), j)

    # the unrotated start is always refined and the best screened others join it; their
    # screening evaluations are kept to start the refinement from (only theirs: memory)
    kept: dict[int, EnergyEvaluation] = {}
    for i, S in enumerate(starts):
        ev = rest if i == len(starts) - 1 else energy.evaluate(S.apply(X0))
        screened[i], kept[i] = ev.energy, ev
        others = [j for j in kept if j != 0]
        if len(others) > max(0, keep - 1):
            del kept[max(others, key=rank)]
    order = [0] + sorted((j for j in kept if j != 0), key=rank)

    refined, finals = {}, {}
    for rank_i, i in enumerate(order):
        S, ev = _refine(energy, X0, starts[i], kept[i], kind == "similarity", iterations)
        refined[i], finals[i] = float(ev.energy), S
        if progress is not None:
            progress(f"candidate {rank_i + 1}/{len(order)}: rotation {rotation_angle(S.R):.0f} deg, "
                     f"energy {screened[i]:.3g} -> {ev.energy:.3g}")
    # orientation prior: keep the unrotated start's alignment unless another start reaches
    # an energy lower by the factor ``switch`` (docs/method.md: on articulated poses the SDF
    # energy alone often prefers a wrong orientation)
    best_other = min(order[1:], key=lambda i: refined[i], default=None)
    best_i = 0
    if best_other is not None and refined[best_other] < switch * refined[0]:
        best_i = best_other
    best = finals[best_i]
    if best_other is not None:
        log.info("orientation prior: best rotated start %.4g, unrotated %.4g (ratio %.2f, switch "
                 "below %.2f)", refined[best_other], refined[0],
                 refined[best_other] / max(refined[0], 1e-300), switch)
    result = InitialAlignment(
        matrix=best.matrix(), scale=float(best.scale), energy=refined[best_i],
        rest_energy=float(rest.energy), candidates=len(starts), chosen=best_i,
        screened_energies=screened, refined_energies=refined, evaluations=energy.evaluations,
        seconds=time.perf_counter() - t0,
    )
    log.info("initial alignment: candidate %d of %d, rotation %.1f deg, scale %.3f, coarse energy "
             "%.4g (rest pose %.4g), %d evaluations in %.2fs", best_i, len(starts),
             rotation_angle(best.R), best.scale, refined[best_i], rest.energy, energy.evaluations,
             result.seconds)
    return result
