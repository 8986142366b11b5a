"""Closest points on triangles, vectorized, in float64."""

from __future__ import annotations

import numpy as np

__all__ = ["closest_point_barycentrics"]


def closest_point_barycentrics(P: np.ndarray, A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of the closest point of triangle ``ABC`` to ``P``, row-wise.

    Ericson, *Real-Time Collision Detection* (2005), section 5.1.5, vectorized: the closest
    point is ``b0 A + b1 B + b2 C`` with ``b >= 0`` and ``b0 + b1 + b2 = 1``.

    Parameters
    ----------
    P, A, B, C : (k, 3) float
        Query points and the corners of the triangle paired with each.

    Returns
    -------
    (k, 3) float64

    Examples
    --------
    >>> A, B, C = np.eye(3)[[0]] * 0, np.eye(3)[[0]], np.eye(3)[[1]]
    >>> closest_point_barycentrics(np.array([[0.25, 0.25, 1.0]]), A, B, C)
    array([[0.5 , 0.25, 0.25]])
    """
    ab, ac = B - A, C - A
    ap, bp, cp = P - A, P - B, P - C
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2

    k = P.shape[0]
    bary = np.empty((k, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        # interior (default)
        denom = va + vb + vc
        v = np.where(denom != 0, vb / denom, 1.0 / 3.0)
        w = np.where(denom != 0, vc / denom, 1.0 / 3.0)
        bary[:] = np.stack([1 - v - w, v, w], axis=1)
        # Regions in Ericson's order; later assignments must not override earlier matches,
        # so we assign in reverse order.
        e43, e56 = d4 - d3, d5 - d6
        s = e43 + e56
        bc = (va <= 0) & (e43 >= 0) & (e56 >= 0)
        wbc = np.where(s != 0, e43 / s, 0.0)
        bary[bc] = np.stack([np.zeros_like(wbc), 1 - wbc, wbc], axis=1)[bc]
        ac_r = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        s = d2 - d6
        wac = np.where(s != 0, d2 / s, 0.0)
        bary[ac_r] = np.stack([1 - wac, np.zeros_like(wac), wac], axis=1)[ac_r]
        c_r = (d6 >= 0) & (d5 <= d6)
        bary[c_r] = (0.0, 0.0, 1.0)
        ab_r = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        s = d1 - d3
        vab = np.where(s != 0, d1 / s, 0.0)
        bary[ab_r] = np.stack([1 - vab, vab, np.zeros_like(vab)], axis=1)[ab_r]
        b_r = (d3 >= 0) & (d4 <= d3)
        bary[b_r] = (0.0, 1.0, 0.0)
        a_r = (d1 <= 0) & (d2 <= 0)
        bary[a_r] = (1.0, 0.0, 0.0)
    return bary
