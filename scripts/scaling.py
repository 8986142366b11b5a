"""Time and peak memory against vertex count and grid resolution, at default settings.

    python scripts/scaling.py [--pose 05] [--vertices 5k 20k 42k 80k] [--grids 32 48 64 96 128]
                              [--big-grid 128] [--out results/scaling]
    make scaling

Meshes: lion-reference and a lion pose from ``../shared/data``, refined by midpoint
subdivision applied to the same faces of both, so vertex ``i`` still corresponds
(``5k`` is the original, ``20k`` one full subdivision, ``80k`` two; ``42k`` subdivides one
full time and then the first faces again until about 42,000 vertices). Without the data, a
generated capsule pair is refined the same way.

Runs, each in a fresh child process: every vertex count at the default grid (64), every grid
resolution on the original mesh, and the 42k mesh at ``--big-grid`` (the 2 GB memory check).
Writes ``<out>/scaling.json``, ``<out>/scaling.md`` and ``<out>/scaling.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _data import ROOT, data_dir  # noqa: E402
from bench import _in_child, run_ours  # noqa: E402

SIZES = {"5k": 0, "20k": 1, "42k": 1.5, "80k": 2}


def refine(V: np.ndarray, F: np.ndarray, T: np.ndarray, level: float):
    """Midpoint-subdivide source ``(V, F)`` and target ``(T, F)`` identically; a fractional
    ``level`` subdivides the first faces once more until ``42/20`` times the vertices."""
    import trimesh

    goal = None
    if level != int(level):
        goal = int(round(42000 * len(V) / 5000))
    for _ in range(int(level)):
        V2, F2 = trimesh.remesh.subdivide(V, F)
        T, _ = trimesh.remesh.subdivide(T, F)
        V, F = V2, F2
    if goal is not None:
        # each subdivided face adds about 1.5 vertices (3 midpoints shared by 2 faces)
        count = min(len(F), int((goal - len(V)) / 1.5))
        idx = np.arange(count)
        V2, F2 = trimesh.remesh.subdivide(V, F, face_index=idx)
        T, _ = trimesh.remesh.subdivide(T, F, face_index=idx)
        V, F = V2, F2
    return np.asarray(V), np.asarray(F), np.asarray(T)


def meshes(pose: str):
    import morphmodes_vol as mm

    data = data_dir()
    if data is None:
        from morphmodes_vol.demo import demo_pair

        (V, F), (T, _) = demo_pair()
        return "capsule (generated)", V, F, T
    lion = data / "lion-poses"
    V, F = mm.as_mesh(lion / "lion-reference.obj", "source")
    T, _ = mm.as_mesh(lion / f"lion-{pose}.obj", "target")
    return f"lion-reference -> lion-{pose}", V, F, T


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pose", default="05")
    ap.add_argument("--vertices", nargs="*", default=list(SIZES), choices=list(SIZES))
    ap.add_argument("--grids", nargs="*", type=int, default=[32, 48, 64, 96, 128])
    ap.add_argument("--big-grid", type=int, default=128)
    ap.add_argument("--out", default=str(ROOT / "results" / "scaling"))
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name, V, F, T = meshes(args.pose)

    runs = [("vertices", size, 64) for size in args.vertices]
    runs += [("grid", "5k", g) for g in args.grids if g != 64 or "5k" not in args.vertices]
    if args.big_grid:
        runs.append(("memory", "42k", args.big_grid))
    rows = []
    print("| series | vertices | grid | wall s | SDF evals | ms / eval | error | peak RSS MB |")
    print("|---|---|---|---|---|---|---|---|", flush=True)
    for series, size, grid in runs:
        Vr, Fr, Tr = refine(V, F, T, SIZES[size])
        r = _in_child(run_ours, (Vr, Fr), (Tr, Fr), (Tr, Fr), {"grid": grid})
        row = {"series": series, "size": size, "vertices": int(len(Vr)), "grid": grid,
               "wall_s": r["wall_s"], "evaluations": r["evaluations"],
               "ms_per_evaluation": 1000 * r["seconds_per_evaluation"], "error": r["error"],
               "peak_rss_mb": r["peak_rss_mb"], "timings": r["timings"]}
        rows.append(row)
        print(f"| {series} | {row['vertices']} | {grid} | {row['wall_s']:.1f} | {row['evaluations']} | "
              f"{row['ms_per_evaluation']:.0f} | {row['error']:.4f} | {row['peak_rss_mb']:.0f} |",
              flush=True)
    (out / "scaling.json").write_text(json.dumps({"pair": name, "rows": rows}, indent=2))
    md = ["| series | vertices | grid | wall s | SDF evals | ms / eval | error | peak RSS MB |",
          "|---|---|---|---|---|---|---|---|"]
    md += [f"| {r['series']} | {r['vertices']} | {r['grid']} | {r['wall_s']:.1f} | {r['evaluations']} | "
           f"{r['ms_per_evaluation']:.0f} | {r['error']:.4f} | {r['peak_rss_mb']:.0f} |" for r in rows]
    (out / "scaling.md").write_text(f"{name}, default settings\n\n" + "\n".join(md) + "\n")
    _plot(rows, out / "scaling.png", name)
    print(f"wrote {out}/scaling.json, scaling.md, scaling.png")
    return 0


def _plot(rows: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    by_n = sorted([r for r in rows if r["grid"] == 64], key=lambda r: r["vertices"])
    by_g = sorted([r for r in rows if r["size"] == "5k"], key=lambda r: r["grid"])
    axes[0].plot([r["vertices"] for r in by_n], [r["wall_s"] for r in by_n], "o-")
    axes[0].set(xlabel="source vertices", ylabel="wall time (s)", title="grid 64", xscale="log")
    axes[1].plot([r["grid"] for r in by_g], [r["wall_s"] for r in by_g], "o-")
    axes[1].set(xlabel="grid resolution", ylabel="wall time (s)", title="original mesh")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


if __name__ == "__main__":
    raise SystemExit(main())
