"""Checking the sign of a target SDF against a closed reference surface."""

from __future__ import annotations

import numpy as np

from .grid import Grid
from .source import signed_distance

__all__ = ["sign_errors"]


def sign_errors(sdf, grid: Grid, V_ref, F_ref, margin: float = 2.0) -> tuple[int, int]:
    """Count the nodes of ``grid`` where ``sdf`` has the wrong sign.

    The reference is a closed mesh (exact ray-parity inside test); only nodes farther than
    ``margin * grid.spacing`` from it are checked, since the sign of a point on the surface
    is a matter of interpolation, not of the sign method.

    Parameters
    ----------
    sdf : TargetSDF
        Anything with ``sample(points (k, 3)) -> (k,)``, negative inside.
    grid : Grid
    V_ref : (n, 3) float
    F_ref : (m, 3) int
        The closed surface the SDF should describe.
    margin : float
        In voxels (grid spacings).

    Returns
    -------
    wrong, checked : int
        Nodes with the wrong sign, nodes checked.

    Examples
    --------
    >>> from morphmodes_vol.primitives import icosphere
    >>> from morphmodes_vol.sdf import Grid, build_target_sdf
    >>> V, F = icosphere(3)
    >>> grid = Grid.covering([-1.3] * 3, [1.3] * 3, 16)
    >>> sign_errors(build_target_sdf(V, F, grid), grid, V, F)
    (0, 2400)
    """
    P = grid.points()
    ref = signed_distance(V_ref, F_ref, P, sign="raycast").value
    far = np.abs(ref) > margin * grid.spacing
    values = sdf.sample(P[far])
    wrong = np.count_nonzero((values < 0) != (ref[far] < 0))
    return int(wrong), int(np.count_nonzero(far))
