"""Time and peak memory against vertex count and grid resolution, at the default settings
(the initial alignment and two starts of ``RegistrationOptions()``).

    python scripts/scaling.py [--pose 05] [--series vertices grid memory]
                              [--vertices 5k 20k 45k 80k] [--grids 32 48 64 96 128]
                              [--big-grid 128] [--out results/scaling] [--set KEY=VALUE ...]
    make scaling

``--set initialization=none`` runs one Levenberg-Marquardt run from the rest pose instead
(the fast path before the initialization stage, which earlier tables used).

Meshes: lion-reference and a lion pose from ``../shared/data``, refined by midpoint
subdivision applied to the same faces of both, so vertex ``i`` still corresponds
(``5k`` is the original, ``20k`` one subdivision, ``80k`` two; ``45k`` splits every
triangle into 9, the 42k class of mesh). Without the data, a
generated capsule pair is refined the same way.

Series (``--series``, all three by default), each run in a fresh child process: ``vertices``,
every vertex count of ``--vertices`` at grid 64; ``grid``, every resolution of ``--grids`` on
the original mesh; ``memory``, the 45k mesh at ``--big-grid`` (the 2 GB memory check).
Writes ``<out>/scaling.json``, ``<out>/scaling.md`` and ``<out>/scaling.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _data import ROOT, data_dir, parse_overrides  # noqa: E402
from bench import _in_child, run_ours  # noqa: E402

SIZES = {"5k": 0, "20k": 1, "45k": "ternary", "80k": 2}
SERIES = ("vertices", "grid", "memory")


def ternary_subdivision(V: np.ndarray, F: np.ndarray, T: np.ndarray):
    """Split every triangle into 9 (each edge in thirds, plus the face centre), applied to
    the source ``(V, F)`` and the target ``(T, F)`` alike; ``n + 2 E + F`` vertices (45k
    on the 5000-vertex lion), closed when the input is, vertex ``i < n`` unchanged."""
    n = len(V)
    half = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])  # face-edge c: (c, c+1)
    edges, inverse = np.unique(np.sort(half, axis=1), axis=0, return_inverse=True)
    inverse = inverse.reshape(3, -1).T  # (f, 3): edge of corner pair (c, c+1)
    ne, nf = len(edges), len(F)

    def points(X):
        a, b = X[edges[:, 0]], X[edges[:, 1]]
        thirds = np.stack([a + (b - a) / 3.0, a + 2.0 * (b - a) / 3.0], 1).reshape(-1, 3)
        return np.concatenate([X, thirds, X[F].mean(axis=1)])

    def third(c: int, near_first: bool) -> np.ndarray:
        """Index of the edge point of face-edge (c, c+1) nearer corner c (or c+1)."""
        lo_first = F[:, c] < F[:, (c + 1) % 3]  # edge stored as (F[c], F[c+1])
        near_lo = lo_first if near_first else ~lo_first
        return n + 2 * inverse[:, c] + np.where(near_lo, 0, 1)

    # barycentric lattice (i, j, k), i + j + k = 3, on corners (v0, v1, v2)
    lattice = {(3, 0, 0): F[:, 0], (0, 3, 0): F[:, 1], (0, 0, 3): F[:, 2],
               (2, 1, 0): third(0, True), (1, 2, 0): third(0, False),
               (0, 2, 1): third(1, True), (0, 1, 2): third(1, False),
               (1, 0, 2): third(2, True), (2, 0, 1): third(2, False),
               (1, 1, 1): n + 2 * ne + np.arange(nf)}
    tris = []
    for i in range(3):
        for j in range(3 - i):
            k = 2 - i - j  # upward triangles
            tris.append(((i + 1, j, k), (i, j + 1, k), (i, j, k + 1)))
    for i in range(2):
        for j in range(2 - i):
            k = 1 - i - j  # downward triangles
            tris.append(((i, j + 1, k + 1), (i + 1, j, k + 1), (i + 1, j + 1, k)))
    F9 = np.concatenate([np.stack([lattice[a], lattice[b], lattice[c]], 1) for a, b, c in tris])
    return points(np.asarray(V, float)), F9, points(np.asarray(T, float))


def refine(V: np.ndarray, F: np.ndarray, T: np.ndarray, level):
    """Midpoint-subdivide source ``(V, F)`` and target ``(T, F)`` identically ``level``
    times, or split each triangle into 9 (``level="ternary"``)."""
    import trimesh

    if level == "ternary":
        return ternary_subdivision(np.asarray(V), np.asarray(F), np.asarray(T))
    for _ in range(int(level)):
        V2, F2 = trimesh.remesh.subdivide(V, F)
        T, _ = trimesh.remesh.subdivide(T, F)
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
    ap.add_argument("--series", nargs="+", default=list(SERIES), choices=SERIES,
                    help="which series to run (default: all)")
    ap.add_argument("--vertices", nargs="+", default=list(SIZES), choices=list(SIZES))
    ap.add_argument("--grids", nargs="+", type=int, default=[32, 48, 64, 96, 128])
    ap.add_argument("--big-grid", type=int, default=128, help="grid of the memory run")
    ap.add_argument("--out", default=str(ROOT / "results" / "scaling"))
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="RegistrationOptions overrides, e.g. initialization=none (one run from "
                         "the rest pose instead of the default settings' two starts)")
    args = ap.parse_args()
    overrides = parse_overrides(args.set)
    settings = ", ".join(args.set) if args.set else "default settings"
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name, V, F, T = meshes(args.pose)

    runs = [("vertices", size, 64) for size in args.vertices] if "vertices" in args.series else []
    if "grid" in args.series:
        runs += [("grid", "5k", g) for g in args.grids if ("vertices", "5k", g) not in runs]
    if "memory" in args.series:
        runs.append(("memory", "45k", args.big_grid))
    rows = []
    print("| series | vertices | grid | wall s | SDF evals | ms / eval | error | peak RSS MB |")
    print("|---|---|---|---|---|---|---|---|", flush=True)
    for series, size, grid in runs:
        Vr, Fr, Tr = refine(V, F, T, SIZES[size])
        r = _in_child(run_ours, (Vr, Fr), (Tr, Fr), (Tr, Fr),
                      {"grid": grid, **overrides})
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
    (out / "scaling.md").write_text(f"{name}, {settings}\n\n" + "\n".join(md) + "\n")
    _plot(rows, out / "scaling.png", f"{name}, {settings}")
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
    axes[0].set_xticks([r["vertices"] for r in by_n], [f"{r['vertices'] / 1000:.0f}k" for r in by_n])
    axes[0].minorticks_off()
    axes[1].plot([r["grid"] for r in by_g], [r["wall_s"] for r in by_g], "o-")
    axes[1].set(xlabel="grid resolution", ylabel="wall time (s)", title="original mesh")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


if __name__ == "__main__":
    raise SystemExit(main())
