"""Dense vs vdb target SDF on one lion pair: how far apart are the registered vertices?

    .venv-vdb/bin/python scripts/backend_difference.py [--pose 01] [--set grid=64 ...]

Registers lion-reference onto lion-<pose> three times with the same options: dense target
grid (``target_grid`` = ``grid``), vdb with the same voxel size, and dense with one node more
along the longest side (``grid + 1``) as a yardstick of how much any small change of the
target field moves the result of Algorithm 1. Prints a markdown table of the ground-truth
errors and the vertex differences (mean and max distance over the pose's bounding-box
diagonal). Needs the OpenVDB environment (``bash dev.sh vdb-env``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _data import data_dir, parse_overrides  # noqa: E402

import morphmodes_vol as mm  # noqa: E402
from morphmodes_vol.mesh import as_mesh, bbox_diagonal  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pose", default="01")
    ap.add_argument("--set", nargs="*", default=[], metavar="OPTION=VALUE")
    args = ap.parse_args()
    data = data_dir()
    if data is None:
        print("shared data not found (set MORPHMODES_DATA)", file=sys.stderr)
        return 1
    src = data / "lion-poses" / "lion-reference.obj"
    tgt = data / "lion-poses" / f"lion-{args.pose}.obj"
    base = mm.RegistrationOptions().replace(**parse_overrides(args.set))
    runs = {
        f"dense, target grid {base.resolved_target_grid}": base,
        "vdb, same voxel size": base.replace(target_backend="vdb"),
        f"dense, target grid {base.resolved_target_grid + 1}": base.replace(target_grid=base.resolved_target_grid + 1),
    }
    diag = bbox_diagonal(as_mesh(tgt)[0])
    results = {}
    for name, options in runs.items():
        t = time.perf_counter()
        results[name] = (mm.register(src, tgt, options, ground_truth=tgt), time.perf_counter() - t)
        print(f"{name}: done in {results[name][1]:.0f}s", file=sys.stderr, flush=True)
    ref = results[next(iter(runs))][0].vertices
    print(f"lion-reference -> lion-{args.pose}, options {' '.join(args.set) or 'defaults'}\n")
    print("| run | ground-truth error | modes | evaluations | status | vs first run: mean | max | wall (s) |")
    print("|---|---|---|---|---|---|---|---|")
    for name, (r, wall) in results.items():
        d = np.linalg.norm(r.vertices - ref, axis=1) / diag
        print(f"| {name} | {r.metrics['ground_truth_error']:.4f} | {r.modes} | {r.evaluations} | "
              f"{r.status} | {d.mean():.4f} | {d.max():.4f} | {wall:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
