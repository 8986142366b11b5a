"""Scan study: registration of each reference mesh onto scans of its poses.

For every pair (reference -> pose) of the sets of ``../shared/data`` the intact pose is
delivered as a scanner would (:mod:`morphmodes_vol.variants`, :mod:`morphmodes_vol.scanner`):

- ``mesh``: the pose mesh itself (the reference row);
- ``cloud``: 40k points drawn uniformly by area, with normals, moved along them by noise of
  0.1% of the diagonal (a full scan, registered as a point cloud);
- ``view1-points`` / ``view1-mesh``: one range scan from the side that sees about half of the
  surface (320 x 240 rays, depth noise 0.1% of the diagonal at one diagonal, grazing
  dropouts), as oriented points and as the range image's mesh;
- ``view2-points`` / ``view2-mesh``: two such scans from opposite sides.

Ours (the defaults, or ``--set``) and RICP+NRICP (trimesh ``nricp_amberg`` after rigid ICP,
which takes point targets too) run on the same target; the error is against the intact pose
(``mean_i ||x_i - pose_i|| / diagonal(pose)``). A failed run is a result: its status is kept.

    python scripts/scan_study.py --quick                  # 2 + 2 pairs
    python scripts/scan_study.py                          # every pair of both sets
    python scripts/scan_study.py --plot-only

Writes ``scan_runs.csv``, ``scan_table.md``, ``scans.png`` and ``scan_picture.png`` (a
single-view scan with the registered reference over it) into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _data import ROOT, SETS, data_dir, mesh_file, parse_overrides, plan, write_csv  # noqa: E402
from _exp import load_rows  # noqa: E402

import morphmodes_vol as mm  # noqa: E402
from morphmodes_vol.mesh import load_mesh  # noqa: E402
from morphmodes_vol.metrics import ground_truth_error  # noqa: E402
from morphmodes_vol.pointcloud import PointCloud  # noqa: E402
from morphmodes_vol.scanner import view_directions, virtual_scan  # noqa: E402
from morphmodes_vol.variants import half_view_direction, sampled_points  # noqa: E402

QUICK = {"tuning": ["lion-01", "cat-03"], "validation": ["dance-04", "jump-03"]}
KINDS = ("mesh", "cloud", "view1-points", "view1-mesh", "view2-points", "view2-mesh")
CLOUD_POINTS, NOISE = 40_000, 1e-3


def scan_target(V, F, kind: str, seed: int):
    """The pose ``(V, F)`` delivered as ``kind``: a mesh ``(V, F)`` or a :class:`PointCloud`."""
    if kind == "mesh":
        return V, F
    if kind == "cloud":
        P, N = sampled_points(V, F, CLOUD_POINTS, noise=NOISE, seed=seed)
        return PointCloud(P, N)
    views, what = kind.split("-")
    scans = virtual_scan(V, F, view_directions(int(views[-1]), half_view_direction(V, F)), noise=NOISE, seed=seed)
    if what == "points":
        return PointCloud(np.vstack([s.points for s in scans]), np.vstack([s.normals for s in scans]))
    offsets = np.cumsum([0] + [len(s.points) for s in scans])
    return np.vstack([s.points for s in scans]), np.vstack([s.faces + o for s, o in zip(scans, offsets)])


def run_ours(source, target, truth, options) -> dict:
    t = time.perf_counter()
    try:
        r = mm.register(source, target, options)
    except Exception as exc:  # noqa: BLE001 - a failure is a result of the study
        return {"status": f"{type(exc).__name__}: {exc}"[:200], "error": float("nan"),
                "seconds": time.perf_counter() - t}, None
    return {"status": r.status, "error": ground_truth_error(r.vertices, truth),
            "seconds": time.perf_counter() - t}, r.vertices


def run_baseline(source, target, truth) -> dict:
    from morphmodes_vol.baselines import nricp, nricp_onto_points

    t = time.perf_counter()
    try:
        if isinstance(target, PointCloud):  # trimesh's NRICP takes points as its target
            X = nricp_onto_points(source, target.points)
            error = ground_truth_error(X, truth)
        else:
            error = nricp(source, target, rigid_first=True, ground_truth=truth).metrics["ground_truth_error"]
    except Exception as exc:  # noqa: BLE001 - a failure is a result of the study
        return {"status": f"{type(exc).__name__}: {exc}"[:200], "error": float("nan"),
                "seconds": time.perf_counter() - t}
    return {"status": "ok", "error": error, "seconds": time.perf_counter() - t}


def table(rows, pairs) -> str:
    cell = {(r["pair"], r["kind"], r["method"]): r for r in rows}
    md = ["| set | pair | target | ours | RICP+NRICP | RICP+NRICP / ours | s (ours) |", "|---|---|---|---|---|---|---|"]
    for p in pairs:
        for k in KINDS:
            o, b = cell.get((p["pair"], k, "ours")), cell.get((p["pair"], k, "ricp+nricp"))
            if o is None and b is None:
                continue
            eo = float(o["error"]) if o else float("nan")
            eb = float(b["error"]) if b else float("nan")
            bcell = f"{eb:.4f}" if b and b["status"] == "ok" else (b["status"][:40] if b else "")
            md.append(f"| {p['set']} | {p['pair']} | {k} | {eo:.4f} | {bcell} | "
                      f"{eb / eo:.2f} | {float(o['seconds']) if o else float('nan'):.0f} |")
    md += ["", "Means over the pairs (ours; RICP+NRICP on the same targets):", ""]
    for s in dict.fromkeys(p["set"] for p in pairs):
        names = [p["pair"] for p in pairs if p["set"] == s]
        for k in KINDS:
            both = [n for n in names if (n, k, "ours") in cell]
            if not both:
                continue
            ours = np.array([float(cell[(n, k, "ours")]["error"]) for n in both])
            base = np.array([float(cell[(n, k, "ricp+nricp")]["error"]) if (n, k, "ricp+nricp") in cell
                             else np.nan for n in both])
            mesh = np.array([float(cell[(n, "mesh", "ours")]["error"]) if (n, "mesh", "ours") in cell
                             else np.nan for n in both])
            worse = [n for n, a, b in zip(both, ours, base) if np.isfinite(b) and a > b]
            line = f"- {s}, {k}: ours {np.nanmean(ours):.4f}"
            if np.isfinite(mesh).any():
                line += f" (worst {np.nanmax(ours / mesh):.2f}x its mesh registration)"
            if np.isfinite(base).any():
                line += (f", RICP+NRICP {np.nanmean(base):.4f} ({np.nanmean(base) / np.nanmean(ours):.2f}x); worse than "
                         f"RICP+NRICP on {len(worse)} of {len(both)}" + (f" ({', '.join(worse)})" if worse else ""))
            md.append(line)
    return "\n".join(md) + "\n"


def plot(rows, pairs, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [p["pair"] for p in pairs]
    fig, ax = plt.subplots(figsize=(max(6, 1.2 * len(names)), 4.5))
    colors = plt.get_cmap("tab10")
    width = 0.8 / len(KINDS)
    for j, k in enumerate(KINDS):
        for method, marker in (("ours", "o"), ("ricp+nricp", "x")):
            xs, ys = [], []
            for i, n in enumerate(names):
                r = next((r for r in rows if r["pair"] == n and r["kind"] == k and r["method"] == method), None)
                if r is not None and np.isfinite(float(r["error"])):
                    xs.append(i + (j - (len(KINDS) - 1) / 2) * width)
                    ys.append(float(r["error"]))
            ax.scatter(xs, ys, marker=marker, s=18, color=colors(j),
                       label=f"{k} ({'ours' if method == 'ours' else 'RICP+NRICP'})")
    ax.set_yscale("log")
    ax.set_xticks(range(len(names)), names, rotation=45, ha="right")
    ax.set_ylabel("ground-truth error (fraction of the diagonal)")
    ax.set_title("Registration onto scans: dots ours, crosses RICP+NRICP")
    ax.legend(fontsize=6, ncol=2)
    ax.grid(True, axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def picture(scan: PointCloud, X: np.ndarray, F: np.ndarray, path: Path) -> None:
    """The scan's points and the registered reference's vertices, two projections."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 4.5))
    for ax, (a, b) in zip(axes, ((0, 1), (2, 1))):
        ax.scatter(X[:, a], X[:, b], s=0.3, color="tab:blue", label="registered reference")
        ax.scatter(scan.points[:, a], scan.points[:, b], s=0.3, color="tab:orange", label="single-view scan")
        ax.set_aspect("equal")
        ax.set_axis_off()
    axes[0].legend(markerscale=20, fontsize=8, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="2 + 2 pairs")
    ap.add_argument("--sets", nargs="+", choices=list(SETS), default=list(SETS))
    ap.add_argument("--pairs", nargs="*", default=[])
    ap.add_argument("--kinds", nargs="+", choices=KINDS, default=list(KINDS))
    ap.add_argument("--methods", nargs="+", choices=["ours", "ricp+nricp"], default=["ours", "ricp+nricp"])
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--out", default=None)
    ap.add_argument("--plot-only", action="store_true")
    args = ap.parse_args()
    if data_dir() is None:
        ap.error("the shared data is needed (../shared/data or MORPHMODES_DATA)")
    out = Path(args.out) if args.out else ROOT / "results" / ("scans_quick" if args.quick else "scans")
    out.mkdir(parents=True, exist_ok=True)
    pairs = plan(args.sets, QUICK if args.quick else None, args.pairs)
    rows = load_rows(out, "scan_runs") if (out / "scan_runs.csv").is_file() else []
    options = mm.RegistrationOptions().replace(**parse_overrides(args.set))
    config = {"ours": json.dumps(options.to_dict(), sort_keys=True), "ricp+nricp": "trimesh nricp_amberg defaults"}
    if not args.plot_only:
        done = {(r["pair"], r["kind"], r["method"]) for r in rows if r.get("config") == config[r["method"]]}
        rows = [r for r in rows if (r["pair"], r["kind"], r["method"]) in done]
        for p in pairs:
            source = load_mesh(mesh_file(p["source"]))
            Vt, Ft = load_mesh(mesh_file(p["target"]))
            for k in args.kinds:
                target = scan_target(Vt, Ft, k, seed=int(p["pair"][-2:]))
                for method in args.methods:
                    if (p["pair"], k, method) in done:
                        continue
                    if method == "ours":
                        res, X = run_ours(source, target, Vt, options)
                        if k == "view1-points" and X is not None and not (out / "scan_picture.png").exists():
                            picture(target, X, source[1], out / "scan_picture.png")
                    else:
                        res = run_baseline(source, target, Vt)
                    size = len(target.points) if isinstance(target, PointCloud) else len(target[1])
                    rows.append({**p, "kind": k, "method": method, "target_size": size, **res, "config": config[method]})
                    print(f"{p['pair']:>11} {k:>13} {method:>10}: {res['error']:.4f} ({res['seconds']:.1f} s) "
                          f"{res['status']}", flush=True)
                    write_csv(out / "scan_runs.csv", rows)
        (out / "meta.json").write_text(json.dumps({"command": sys.argv, "options": json.loads(config["ours"])},
                                                  indent=2) + "\n")
    present = [p for p in pairs if any(r["pair"] == p["pair"] for r in rows)]
    text = table(rows, present)
    (out / "scan_table.md").write_text(text)
    if rows:
        plot(rows, present, out / "scans.png")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
