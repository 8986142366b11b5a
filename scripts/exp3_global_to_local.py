"""Experiment 3, global to local (the paper's donkey-to-horse figure, here on the lion or
cat poses): one registration with ours, and the registered mesh at the end of every stage
of the adaptive scheme (1, 2, ... m_max modes).

    python scripts/exp3_global_to_local.py --source lion-reference --target lion-02 --grid 48 --strip 1 2 3 5 10 20

Writes results/exp3_global_to_local/: exp3_stages.{csv,md} (per stage: ground-truth error,
SDF residual, surface distance, degeneracy, cumulative SDF evaluations), exp3_strip.png
(the meshes after the stages in ``--strip``), exp3_stages.png (error and residual vs modes),
meshes.npz, meta.json.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _exp import MeshStore, add_common, line_plot, load_rows, options_from, save_meta, start, write_table  # noqa: E402

import morphmodes_vol as mm  # noqa: E402
from morphmodes_vol.eigenbasis import LBSBasis  # noqa: E402
from morphmodes_vol.mesh import load_mesh  # noqa: E402
from morphmodes_vol.metrics import sdf_residual, shape_metrics, vertex_errors  # noqa: E402
from morphmodes_vol.render import Panel, render_panels  # noqa: E402

COLUMNS = [("modes", "modes", "{:.0f}"), ("end", "stage end", "{}"), ("evaluations", "SDF evaluations (cumulative)", "{:.0f}"),
           ("ground_truth_error", "GT error", "{:.4f}"), ("final_sdf_rms", "SDF RMS", "{:.4f}"),
           ("surface_mean", "surface mean", "{:.4f}"), ("flipped_fraction", "flipped", "{:.3%}"),
           ("volume_ratio", "volume ratio", "{:.3f}")]


def plots(out: Path, rows: list[dict], store: MeshStore, source: Path, target: Path, strip: list[int]) -> None:
    m = [r["modes"] for r in rows]
    line_plot(out / "exp3_stages.png",
              [(m, [r["ground_truth_error"] for r in rows], "o-", "ground-truth error", {}),
               (m, [r["final_sdf_rms"] for r in rows], "s--", "SDF residual RMS", {})],
              "modes (end of stage)", "fraction of the diagonal")

    V0, F = load_mesh(source)
    Vt, Ft = load_mesh(target)
    panels = [Panel(V0, F, f"source {source.stem}")]
    for k in strip:
        if f"stage_{k}" in store:
            V = store[f"stage_{k}"]
            e = vertex_errors(V, Vt)
            panels.append(Panel(V, F, f"{k} mode{'s' if k > 1 else ''} ({e.mean():.3f})", e))
    panels.append(Panel(Vt, Ft, f"target {target.stem}"))
    render_panels(panels, out / "exp3_strip.png", columns=min(len(panels), 4), panel_size=2.2, dpi=80,
                  suptitle="after each stage of the adaptive scheme; color: per-vertex ground-truth error (title: mean)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--source", default="lion-reference")
    ap.add_argument("--target", default="lion-02")
    ap.add_argument("--strip", type=int, nargs="*", default=[1, 2, 3, 5, 10, 20], help="stages drawn")
    add_common(ap)
    args, out, store, source, target = start(ap, "exp3_global_to_local")
    if args.plot_only:
        plots(out, load_rows(out, "exp3_stages"), store, source, target, args.strip)
        return 0

    options = options_from(args)
    save_meta(out, command=sys.argv, options=options.to_dict(), source=source, target=target)
    Vt, _ = load_mesh(target)
    reg = mm.Registration(source, target, options)
    result = reg.run(ground_truth=Vt)
    h = result.history
    basis = LBSBasis(reg.X0, reg.weights)
    truth = reg.normalization.apply(Vt)
    rows = []
    evals = np.cumsum(h.stage_evaluations)
    for T, end, ev in zip(h.stage_coefficients, h.stage_ends, evals):
        X = basis.deform(T)
        row = {"modes": T.shape[0], "end": end, "evaluations": int(ev),
               "final_sdf_rms": sdf_residual(X, reg.source_faces, reg.Q, reg.g, sign=options.source_sign)}
        row.update(shape_metrics(reg.X0, X, reg.source_faces, reg.Y, reg.target_faces, truth))
        rows.append(row)
        store[f"stage_{T.shape[0]}"] = reg.normalization.undo(X)
        print(f"{T.shape[0]} modes ({end}): error {row['ground_truth_error']:.4f}, "
              f"SDF RMS {row['final_sdf_rms']:.4f}", flush=True)
    write_table(rows, out, "exp3_stages", COLUMNS)
    plots(out, rows, store, source, target, args.strip)
    print((out / "exp3_stages.md").read_text())
    print(f"identity error {result.metrics['identity_error']:.4f}; {result.evaluations} evaluations, "
          f"optimize {result.timings['optimize']:.0f}s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
