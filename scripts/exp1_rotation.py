"""Experiment 1, robustness to the initial orientation (the paper's perturbation study).

Rotate the source (lion reference) about its forward axis (z, its longest side) through its
bounding-box center by each angle, register it onto a pose with RICP+NRICP and with ours
(``--methods``; ``nricp`` adds NRICP without rigid ICP), and measure the ground-truth error
(pose vertex i is where reference vertex i belongs). ``--resume`` keeps the runs already in
the output folder and adds the missing ones.

    python scripts/exp1_rotation.py --target lion-01 --angles -30 -20 -10 0 10 20 30 --grid 48

Writes results/exp1_rotation/: exp1_runs.{csv,md} (every metric of every run),
exp1_summary.md (error per angle and the mean ratio), exp1_error_vs_angle.png,
exp1_renders.png, meshes.npz, meta.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _exp import (METRIC_COLUMNS, MeshStore, add_common, line_plot, load_rows, options_from,  # noqa: E402
                  rotated_source, row_of, save_meta, start, write_table)

import morphmodes_vol as mm  # noqa: E402
from morphmodes_vol.baselines import nricp, prepare_pair  # noqa: E402
from morphmodes_vol.mesh import load_mesh  # noqa: E402
from morphmodes_vol.metrics import vertex_errors  # noqa: E402
from morphmodes_vol.render import Panel, render_panels  # noqa: E402

METHODS = ("nricp", "ricp+nricp", "ours")


def summary(rows: list[dict]) -> str:
    angles = sorted({r["angle"] for r in rows})
    err = {(r["angle"], r["method"]): r["ground_truth_error"] for r in rows}
    alone = all((a, "nricp") in err for a in angles)
    md = ["| angle (deg) | identity error | " + ("NRICP error | " if alone else "")
          + "RICP+NRICP error | ours error | RICP+NRICP / ours |",
          "|---|---|---|---|---|" + ("---|" if alone else "")]
    ratios, a_errs, b_errs, c_errs = [], [], [], []
    for a in angles:
        if (a, "ours") not in err or (a, "ricp+nricp") not in err:
            continue
        e_n, e_o = err[(a, "ricp+nricp")], err[(a, "ours")]
        ident = next(r["identity_error"] for r in rows if r["angle"] == a)
        ratios.append(e_n / e_o)
        a_errs.append(e_n)
        b_errs.append(e_o)
        cell = ""
        if alone:
            c_errs.append(err[(a, "nricp")])
            cell = f"{c_errs[-1]:.4f} | "
        md.append(f"| {a:+.0f} | {ident:.4f} | {cell}{e_n:.4f} | {e_o:.4f} | {e_n / e_o:.2f} |")
    if ratios:
        cell = f"{np.mean(c_errs):.4f} | " if alone else ""
        md.append(f"| **mean** | | {cell}{np.mean(a_errs):.4f} | {np.mean(b_errs):.4f} | "
                  f"{np.mean(a_errs) / np.mean(b_errs):.2f} (mean of ratios {np.mean(ratios):.2f}) |")
    return "\n".join(md) + "\n"


def plots(out: Path, rows: list[dict], store: MeshStore, source: Path, target: Path, axis: int,
          render_angles: list[float]) -> None:
    series = []
    for method, style in zip(METHODS, ("^-.", "o--", "s-")):
        pts = sorted((r["angle"], r["ground_truth_error"]) for r in rows if r["method"] == method)
        if pts:
            series.append((*zip(*pts), style, method, {}))
    pts = sorted({(r["angle"], r["identity_error"]) for r in rows})
    series.append((*zip(*pts), ":", "identity (no registration)", {"color": "gray"}))
    line_plot(out / "exp1_error_vs_angle.png", series, "initial rotation about the forward axis (degrees)",
              "ground-truth error / target diagonal", dpi=100)

    V0, F = load_mesh(source)
    Vt, Ft = load_mesh(target)
    done = [m for m in METHODS if any(r["method"] == m for r in rows)]
    panels = []
    for a in render_angles:
        if not all(f"{m}_{a:+.0f}" in store for m in done):
            continue
        panels.append(Panel(rotated_source(V0, axis, a), F, f"source rotated {a:+.0f}"))
        panels.append(Panel(Vt, Ft, f"target {target.stem}"))
        for m in done:
            V = store[f"{m}_{a:+.0f}"]
            e = vertex_errors(V, Vt)
            panels.append(Panel(V, F, f"{m} ({e.mean():.3f})", e))
    if panels:
        render_panels(panels, out / "exp1_renders.png", columns=2 + len(done), panel_size=2.2, dpi=80,
                      suptitle="color: per-vertex ground-truth error (title: mean)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--source", default="lion-reference")
    ap.add_argument("--target", default="lion-01")
    ap.add_argument("--angles", type=float, nargs="+", default=[-30, -20, -10, 0, 10, 20, 30])
    ap.add_argument("--axis", type=int, default=2, help="forward axis (0=x, 1=y, 2=z; the lion's is z)")
    ap.add_argument("--render-angles", type=float, nargs="*", default=None,
                    help="angles drawn in exp1_renders.png (default: first, 0 if run, last)")
    ap.add_argument("--methods", nargs="+", choices=METHODS, default=["ricp+nricp", "ours"],
                    help="methods run at every angle (nricp: NRICP without rigid ICP)")
    ap.add_argument("--resume", action="store_true",
                    help="keep the runs already in the output folder (same options) and add the missing ones")
    add_common(ap)
    args, out, store, source, target = start(ap, "exp1_rotation")
    render_angles = args.render_angles
    if render_angles is None:
        render_angles = sorted({args.angles[0], args.angles[-1]} | ({0.0} & set(args.angles)))
    if args.plot_only:
        rows = load_rows(out, "exp1_runs")
        plots(out, rows, store, source, target, args.axis, render_angles)
        print(summary(rows))
        return 0

    options = options_from(args)
    rows = []
    if args.resume:  # keep the runs already made with the same options
        store = MeshStore(out, reset=False)
        meta = json.loads((out / "meta.json").read_text())
        if meta["options"] != options.to_dict() or Path(meta["target"]).name != target.name:
            sys.exit(f"{out}: earlier runs used other options or another target; run without --resume")
        rows = load_rows(out, "exp1_runs")
    else:
        save_meta(out, command=sys.argv, options=options.to_dict(), source=source, target=target)
    V0, F = load_mesh(source)
    Vt, _ = load_mesh(target)
    columns = [("angle", "angle", "{:+.0f}"), ("method", "method", "{}"),
               ("identity_error", "identity error", "{:.4f}")] + METRIC_COLUMNS
    for angle in args.angles:
        Vs = rotated_source(V0, args.axis, angle)
        for method in args.methods:
            key = f"{method}_{angle:+.0f}"
            if key in store and any(r["angle"] == angle and r["method"] == method for r in rows):
                continue
            t = time.perf_counter()
            extra = {}
            if method == "ours":
                r = mm.register((Vs, F), target, options, ground_truth=Vt)
                extra = {"evaluations": r.evaluations, "status": r.status}
            else:
                r = nricp((Vs, F), target, rigid_first=method == "ricp+nricp", ground_truth=Vt,
                          pair=prepare_pair((Vs, F), target, options))
            rows.append(row_of(r, angle=angle, method=method, identity_error=r.metrics["identity_error"],
                               seconds_wall=time.perf_counter() - t, **extra))
            store[key] = r.vertices
            print(f"angle {angle:+.0f} {method}: identity {rows[-1]['identity_error']:.4f} -> "
                  f"{rows[-1]['ground_truth_error']:.4f} ({rows[-1]['seconds_wall']:.0f}s)", flush=True)
            write_table(rows, out, "exp1_runs", columns)
    rows.sort(key=lambda r: (r["angle"], METHODS.index(r["method"])))
    write_table(rows, out, "exp1_runs", columns)
    text = summary(rows)
    (out / "exp1_summary.md").write_text(text)
    plots(out, rows, store, source, target, args.axis, render_angles)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
