"""Wrong-sign fractions of the target-SDF sign methods on a sphere with holes.

    python scripts/sign_study.py [--resolutions 64 128] [--backends dense vdb]

For each backend, sign method (``winding``: generalized winding number, ``raycast``: ray
parity; for vdb, ``raycast`` keeps OpenVDB's own flood-fill sign in the band) and
resolution, builds the target SDF of :func:`morphmodes_vol.primitives.holed_sphere` (518 of
5120 faces removed, three holes) on a grid over ``[-1.3, 1.3]^3`` and counts the grid nodes
more than two voxels from the (closed) sphere whose sign differs from the closed sphere's.
Prints a markdown table. The vdb rows need the OpenVDB environment (``bash dev.sh vdb-env``).
"""

from __future__ import annotations

import argparse
import sys

from morphmodes_vol.primitives import holed_sphere, icosphere
from morphmodes_vol.sdf import Grid, build_target_sdf
from morphmodes_vol.sdf.signs import sign_errors


def holed_sphere_sign_errors(backend: str, sign: str, resolution: int) -> tuple[int, int]:
    """``(wrong, checked)`` nodes of the holed sphere's SDF (see the module docstring)."""
    V, F = holed_sphere()
    grid = Grid.covering([-1.3] * 3, [1.3] * 3, resolution)
    sdf = build_target_sdf(V, F, grid, backend, sign)
    return sign_errors(sdf, grid, *icosphere(4))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolutions", nargs="*", type=int, default=[64, 128])
    ap.add_argument("--backends", nargs="*", default=["dense", "vdb"], choices=["dense", "vdb"])
    args = ap.parse_args()
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
