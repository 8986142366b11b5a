"""Correspondences from the reverse registration (``two_way``; docs/method.md, "The stages of a
registration").

Registering the target onto the source deforms the target mesh ``(Y, G)`` into ``Yd``, which
lies on the source's surface. Each source vertex ``x_i`` then has a counterpart on the
target: find the closest point of the deformed target to ``x_i`` (a face of ``G`` and
barycentrics ``b``) and take the same barycentric point of the *undeformed* target,
``p_i = sum_c b_c Y[G[f, c]]`` (:func:`reverse_correspondences`). Read the other way, each
deformed target vertex ``Yd_j`` has a closest point on the source's surface, which should land
on ``Y_j``. Both are closest points as barycentric rows (:func:`closest_point_rows`).
:meth:`Registration.run` fits the subspace to the first, and to both stacked
(:meth:`~morphmodes_vol.eigenbasis.LBSBasis.fit`), and lets Levenberg-Marquardt minimize the
objective from each fit: starts that the forward runs cannot reach on some poses.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from .sdf import closest_points

if TYPE_CHECKING:
    from .register import Registration, RegistrationResult
    from .runs import StartRun

__all__ = ["reverse_correspondences", "closest_point_rows", "reverse_grid", "two_way_pass"]

log = logging.getLogger(__name__)


def reverse_correspondences(X: np.ndarray, deformed: np.ndarray, faces: np.ndarray,
                            rest: np.ndarray) -> np.ndarray:
    """Where each point of ``X`` lands on the target, read off a registration of the
    target onto ``X``'s surface.

    Parameters
    ----------
    X : (n, 3) float
        Source vertices (the frame of ``deformed``).
    deformed : (k, 3) float
        The target's vertices after registering the target onto the source.
    faces : (g, 3) int
        The target's faces.
    rest : (k, 3) float
        The target's vertices as given (the frame the output is in).

    Returns
    -------
    (n, 3) float64
        For each ``X[i]``: the point of ``(rest, faces)`` with the barycentric coordinates, on
        the same face, of the closest point of ``(deformed, faces)`` to ``X[i]``.

    Examples
    --------
    >>> tri = np.array([[0, 1, 2]]); Y = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0]])
    >>> reverse_correspondences(np.array([[0.25, 0.25, 0.5]]), Y, tri, 2 * Y + [0, 0, 1])
    array([[0.5, 0.5, 1. ]])
    """
    rest = np.asarray(rest, dtype=np.float64)
    if np.shape(deformed) != rest.shape:
        raise ValueError(f"deformed {np.shape(deformed)} and rest {rest.shape} vertices differ in shape")
    return closest_point_rows(deformed, faces, X) @ rest


def closest_point_rows(X: np.ndarray, faces: np.ndarray, points: np.ndarray) -> sp.csr_matrix:
    """The closest point of the mesh ``(X, faces)`` to each of ``points``, as a row of
    barycentric coordinates over the mesh's vertices: ``rows @ X`` are those closest points,
    and ``rows @ x`` the same surface points after the vertices move to ``x``.

    Parameters
    ----------
    X : (n, 3) float
    faces : (f, 3) int
    points : (k, 3) float

    Returns
    -------
    (k, n) scipy.sparse.csr_matrix
        Three entries per row, summing to 1.

    Examples
    --------
    >>> tri = np.array([[0, 1, 2]]); X = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0]])
    >>> closest_point_rows(X, tri, np.array([[0.5, 0.5, 2.0]])).toarray()
    array([[0. , 0.5, 0.5]])
    """
    X = np.asarray(X, dtype=np.float64)
    faces = np.asarray(faces)
    cp = closest_points(X, faces, np.asarray(points, dtype=np.float64))
    k = cp.faces.shape[0]
    return sp.csr_matrix((cp.barycentrics.ravel(), faces[cp.faces].ravel(), np.arange(0, 3 * k + 1, 3)),
                         shape=(k, X.shape[0]))


def reverse_grid(options) -> int:
    """The reverse registration's ``grid``: ``two_way_grid``, else three quarters of ``grid``
    (the reverse registration only proposes starts; the runs from them are on ``grid``)."""
    return options.two_way_grid if options.two_way_grid is not None else max(4, round(0.75 * options.grid))


def two_way_pass(reg: "Registration", forward: "StartRun",
                 progress) -> tuple["RegistrationResult", list["StartRun"], dict]:
    """``two_way`` (docs/method.md, "The stages of a registration"): register the target onto the
    source, fit the subspace to the correspondences it implies, in two ways: the source
    vertices' counterparts on the target
    (:func:`~morphmodes_vol.two_way.reverse_correspondences`), and those stacked with the
    target vertices' counterparts on the source's surface
    (:func:`~morphmodes_vol.two_way.closest_point_rows`); minimize the objective from
    each fit on all modes (one stage of at most ``two_way_iterations`` Levenberg-Marquardt
    steps); and compare with the ``forward`` run's result by the objective on the full
    grid. Returns the reverse registration, the two runs and the report
    (``metrics["two_way"]``)."""
    o = reg.options
    log.info("two-way: registering the target onto the source")
    grid = reverse_grid(o)
    reverse = type(reg)((reg.target_vertices, reg.target_faces),  # a registration the other way
                        (reg.source_vertices, reg.source_faces),
                        o.replace(two_way=False, grid=grid, source_sign=reg.asked_sign))
    shown = None if progress is None else (  # "[reverse: rest (coarse)] ..." and so on
        lambda e: progress(replace(e, start=f"reverse: {e.start}" if e.start else "reverse")))
    back = reverse.run(progress=shown)
    # the reverse result lies on the source's surface, in the source's original frame
    Yd = reg.normalization.apply(back.vertices)
    P = reverse_correspondences(reg.X0, Yd, reg.target_faces, reg.Y)
    S = closest_point_rows(reg.X0, reg.source_sdf_faces, Yd)
    both = sp.vstack([sp.identity(reg.X0.shape[0], format="csr"), S], format="csr")
    fits = {"reverse": reg.basis.fit(P, o.modes),
            "reverse, both sides": reg.basis.fit(np.vstack([P, reg.Y]), o.modes, rows=both)}
    options = o.replace(initial_modes=o.modes, lm_final_iterations=o.two_way_iterations)
    runs = reg.runner.run([(label, T, options) for label, T in fits.items()], progress)
    objectives = {"forward": reg.runner.full_grid_objective(forward), **{r.label: r.energy for r in runs}}
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
