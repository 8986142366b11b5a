"""Wrong-sign fractions of the target-SDF sign methods on a sphere with holes.

    python scripts/sign_study.py [--resolutions 64 128] [--backends dense vdb] [--by-hole]

For each backend, sign method (``winding``: generalized winding number, ``raycast``: ray
parity; for vdb, ``raycast`` keeps OpenVDB's own flood-fill sign in the band) and
resolution, builds the target SDF of :func:`morphmodes_vol.primitives.holed_sphere` (518 of
5120 faces removed, three holes) on a grid over ``[-1.3, 1.3]^3`` and counts the grid nodes
more than two voxels from the (closed) sphere whose sign differs from the closed sphere's.
Prints a markdown table. The vdb rows need the OpenVDB environment (``bash dev.sh vdb-env``).
``--by-hole`` instead groups the wrong nodes of the dense winding-number SDF by the hole
whose direction is nearest (within 0.7 rad, else "none") and gives their largest distance
from the sphere.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from morphmodes_vol.primitives import holed_sphere, icosphere
from morphmodes_vol.sdf import Grid, build_target_sdf
from morphmodes_vol.sdf.signs import sign_errors
from morphmodes_vol.sdf.source import signed_distance

# hole directions and angular radii of holed_sphere()
_HOLES = np.array([[1.0, 0.2, 0.1], [-0.3, 1.0, 0.4], [0.2, -0.5, -1.0]])
_ANGLES = (0.2, 0.35, 0.5)


def holed_sphere_sign_errors(backend: str, sign: str, resolution: int) -> tuple[int, int]:
    """``(wrong, checked)`` nodes of the holed sphere's SDF (see the module docstring)."""
    V, F = holed_sphere()
    grid = Grid.covering([-1.3] * 3, [1.3] * 3, resolution)
    sdf = build_target_sdf(V, F, grid, backend, sign)
    return sign_errors(sdf, grid, *icosphere(4))


def by_hole(resolution: int) -> str:
    """Where the wrong signs of the dense winding-number SDF lie (same nodes as sign_errors)."""
    V, F = holed_sphere()
    grid = Grid.covering([-1.3] * 3, [1.3] * 3, resolution)
    P = grid.points()
    ref = signed_distance(*icosphere(4), P, sign="raycast").value
    far = np.abs(ref) > 2 * grid.spacing
    values = build_target_sdf(V, F, grid, "dense", "winding").sample(P[far])
    wrong = P[far][(values < 0) != (ref[far] < 0)]
    u = wrong / np.linalg.norm(wrong, axis=1, keepdims=True)
    dirs = _HOLES / np.linalg.norm(_HOLES, axis=1, keepdims=True)
    ang = np.arccos(np.clip(u @ dirs.T, -1, 1))
    hole = np.where(ang.min(axis=1) < 0.7, ang.argmin(axis=1), -1)
    counts = ", ".join(f"hole {a} rad: {int((hole == k).sum())}" for k, a in enumerate(_ANGLES))
    depth = float(np.abs(np.linalg.norm(wrong, axis=1) - 1).max()) if len(wrong) else 0.0
    return (f"{resolution}^3: {len(wrong)} wrong ({counts}, none: {int((hole == -1).sum())}); "
            f"largest distance from the sphere {depth:.3f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolutions", nargs="*", type=int, default=[64, 128])
    ap.add_argument("--backends", nargs="*", default=["dense", "vdb"], choices=["dense", "vdb"])
    ap.add_argument("--by-hole", action="store_true")
    args = ap.parse_args()
    if args.by_hole:
        for res in args.resolutions:
            print(by_hole(res), flush=True)
        return 0
    print("| backend | sign | resolution | nodes checked | wrong signs | fraction |")
    print("|---|---|---|---|---|---|")
    for backend in args.backends:
        for sign in ("winding", "raycast"):
            for res in args.resolutions:
                wrong, checked = holed_sphere_sign_errors(backend, sign, res)
                print(f"| {backend} | {sign} | {res} | {checked} | {wrong} | {wrong / checked:.4%} |",
                      flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
