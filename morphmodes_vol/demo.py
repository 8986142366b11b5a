"""The built-in demo pair: a capsule onto a bent, stretched copy of itself (known answer)."""

from __future__ import annotations

import numpy as np

from .primitives import bend, capsule

__all__ = ["demo_pair"]


def demo_pair() -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """Source capsule and target = the same capsule stretched by 1.2 along its axis, bent by
    70 degrees and shifted; vertex ``i`` of the target is where vertex ``i`` of the source
    should land.

    Returns
    -------
    (V_source (n, 3), F (m, 3)), (V_target (n, 3), F (m, 3))
    """
    V, F = capsule(height=1.0, radius=0.22, count=(24, 24))
    T = V * np.array([1.0, 1.0, 1.2])
    T = bend(T, np.deg2rad(70.0), axis=2, towards=0)
    T = T + np.array([0.05, -0.03, 0.02])
    return (V, F), (T, F.copy())
