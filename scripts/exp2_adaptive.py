"""Experiment 2, necessity of the adaptive scheme (the paper's full-space, Dirichlet and
fixed-subspace comparisons): on one pair, register with

- full space, unregularized (every vertex free, Eq. 3 alone);
- full space + Dirichlet ``w/2 (x - x0)^T L (x - x0)`` for each weight ``w`` of a sweep;
- fixed subspaces of k modes (all active from the start), e.g. 1, 10, 70;
- ours, adaptive (Algorithm 1),

and report ground-truth error and degeneracy (collapsed and flipped triangles, volume
ratio) per method.

    python scripts/exp2_adaptive.py --target lion-01 --grid 48 --weights 1e-4 1e-3 1e-2 --fixed 1 10 70

Writes results/exp2_adaptive/: exp2_methods.{csv,md}, exp2_bars.png, exp2_renders.png,
meshes.npz, meta.json.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _exp import (METRIC_COLUMNS, MeshStore, add_common, load_rows, options_from, row_of,  # noqa: E402
                  save_meta, start, write_table)

import morphmodes_vol as mm  # noqa: E402
from morphmodes_vol.baselines import fixed_subspace, full_space_sdf, prepare_pair  # noqa: E402
from morphmodes_vol.baselines.result import pair_metrics  # noqa: E402
from morphmodes_vol.mesh import load_mesh  # noqa: E402
from morphmodes_vol.metrics import vertex_errors  # noqa: E402
from morphmodes_vol.render import Panel, render_panels  # noqa: E402

COLUMNS = [("method", "method", "{}"), ("iterations", "steps", "{:.0f}"),
           ("evaluations", "SDF evaluations", "{:.0f}"), ("status", "status", "{}")] + METRIC_COLUMNS


def plots(out: Path, rows: list[dict], store: MeshStore, source: Path, target: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [r["method"] for r in rows]
    x = np.arange(len(rows))
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    axes[0].bar(x, [r["ground_truth_error"] for r in rows], color="tab:blue")
    axes[0].axhline(rows[0]["identity_error"], color="gray", ls=":", label="identity")
    axes[0].set_ylabel("GT error / target diagonal")
    axes[0].legend(fontsize=8)
    axes[1].bar(x - 0.2, [100 * r["flipped_fraction"] for r in rows], 0.4, label="flipped")
    axes[1].bar(x + 0.2, [100 * r["collapsed_fraction"] for r in rows], 0.4, label="collapsed")
    axes[1].set_ylabel("% of triangles")
    axes[1].legend(fontsize=8)
    for ax in axes:
        ax.set_xticks(x, names, rotation=40, ha="right", fontsize=8)
        ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(out / "exp2_bars.png", dpi=90)
    plt.close(fig)

    V0, F = load_mesh(source)
    Vt, Ft = load_mesh(target)
    panels = [Panel(V0, F, f"source {source.stem}"), Panel(Vt, Ft, f"target {target.stem}")]
    for r in rows:
        if r["method"] in store:
            V = store[r["method"]]
            e = vertex_errors(V, Vt)
            panels.append(Panel(V, F, f"{r['method']} ({e.mean():.3f})", e))
    render_panels(panels, out / "exp2_renders.png", columns=4, panel_size=2.2, dpi=80,
                  suptitle="color: per-vertex ground-truth error (title: mean)")


def reused_adaptive(exp1: Path, pair, options, target: Path, Vt):
    """Experiment 1's angle-0 run of ours, checked to have the same pair and options; its
    metrics recomputed on this pair (:func:`pair_metrics`)."""
    import json
    from types import SimpleNamespace

    meta = json.loads((exp1 / "meta.json").read_text())
    if meta["options"] != options.to_dict() or Path(meta["target"]).name != target.name:
        sys.exit(f"{exp1}: experiment 1 ran other options or another target; run without --adaptive-from")
    row = next(r for r in load_rows(exp1, "exp1_runs") if r["method"] == "ours" and r["angle"] == 0)
    V = MeshStore(exp1, reset=False)["ours_+0"]
    return SimpleNamespace(vertices=V, metrics=pair_metrics(pair, V, Vt), timings={"total": row["seconds"]},
                           steps="", evaluations=row["evaluations"], status=row["status"] + " (exp1)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--source", default="lion-reference")
    ap.add_argument("--target", default="lion-01")
    ap.add_argument("--weights", type=float, nargs="*", default=[1e-4, 1e-3, 1e-2],
                    help="Dirichlet weights (normalized units, a length^3); 0 (unregularized) always runs")
    ap.add_argument("--fixed", type=int, nargs="*", default=[1, 10, 70], help="fixed subspace sizes")
    ap.add_argument("--full-iterations", type=int, default=300, help="gradient steps of the full-space runs")
    ap.add_argument("--fixed-iterations", type=int, default=300, help="gradient steps of the fixed-subspace runs")
    ap.add_argument("--adaptive-from", default=None, metavar="EXP1_DIR",
                    help="take the adaptive run from experiment 1's unrotated run (angle 0, same pair "
                         "and options) instead of registering again; its metrics are recomputed here")
    add_common(ap)
    args, out, store, source, target = start(ap, "exp2_adaptive")
    if args.plot_only:
        plots(out, load_rows(out, "exp2_methods"), store, source, target)
        return 0

    options = options_from(args)
    save_meta(out, command=sys.argv, options=options.to_dict(), source=source, target=target)
    Vt, _ = load_mesh(target)
    rows = []

    def record(name: str, r, **extra) -> None:
        rows.append(row_of(r, method=name, identity_error=r.metrics["identity_error"], **extra))
        store[name] = r.vertices
        print(f"{name}: error {r.metrics['ground_truth_error']:.4f}, flipped "
              f"{r.metrics['flipped_fraction']:.2%}, collapsed {r.metrics['collapsed_fraction']:.2%}, "
              f"volume {r.metrics['volume_ratio']:.3f}, {rows[-1]['seconds']:.0f}s", flush=True)
        write_table(rows, out, "exp2_methods", COLUMNS)

    pair = prepare_pair(source, target, options)
    full = options.replace(max_iterations=args.full_iterations)
    for w in [0.0] + [w for w in args.weights if w > 0]:
        r = full_space_sdf(source, target, dirichlet=w, options=full, ground_truth=Vt, pair=pair)
        name = "full space" if w == 0 else f"full + Dirichlet {w:g}"
        record(name, r, iterations=r.info["iterations"], evaluations=r.info["evaluations"], status=r.status)
    fixed = options.replace(max_iterations=args.fixed_iterations)
    for k in args.fixed:
        r = fixed_subspace(source, target, k, options=fixed, ground_truth=Vt)
        record(f"fixed {k} modes", r, iterations=len(r.history.step_rms), evaluations=r.evaluations,
               status=r.status)
    name = f"adaptive (ours, {options.modes} modes)"
    if args.adaptive_from:
        r = reused_adaptive(Path(args.adaptive_from), pair, options, target, Vt)
        record(name, r, iterations=r.steps, evaluations=r.evaluations, status=r.status)
    else:
        r = mm.register(source, target, options, ground_truth=Vt)
        record(name, r, iterations=len(r.history.step_rms), evaluations=r.evaluations, status=r.status)
    plots(out, rows, store, source, target)
    print((out / "exp2_methods.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
