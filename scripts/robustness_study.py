"""Robustness study: is the registration a stable function of the geometry?

For every pair, K copies of the source (copy 0 as loaded, copies 1..K-1 with every vertex
moved by N(0, (1e-7 diagonal)^2), seeded) are registered onto five variants of the target
(:mod:`morphmodes_vol.variants`): ``original``; ``retriangulated`` (quadric decimation to
25% of the faces); ``dense`` (each face split into 16); ``noisy`` (re-triangulated, then moved
along the normals by N(0, 0.3% of the diagonal)); ``partial`` (the faces facing one view direction,
about half of the area); on request ``no-bridges`` (without the triangles spanning the
surface, ``repair.bridge_faces``: the face poses). The error is against the intact pose
(vertex i of the reference belongs at vertex i of the pose):
``mean_i ||x_i - pose_i|| / diagonal(pose)``.
RICP+NRICP (trimesh ``nricp_amberg`` after rigid ICP) runs once per pair and variant on the
same target, in a process of its own under a memory cap (``--baseline-memory-gb``): a run
that exceeds it is recorded as "out of memory".

    python scripts/robustness_study.py --quick              # 4 + 4 pairs, K = 3 (about an hour)
    python scripts/robustness_study.py                      # every pair of both sets, K = 5
    python scripts/robustness_study.py --quick --set warped_hops=0 --out results/robust_nohops
    python scripts/robustness_study.py --plot-only

Sets (``../shared/data``, its README): ``tuning`` (lion and cat, reference onto every pose)
and ``validation`` (dance, jump, chicken and face, reference onto every frame).

Runs are appended to ``<out>/robustness_runs.csv`` as they finish, each with the branches
its registration took (``decisions``: the start kept, the runs stopped and why, the warped
pass's choice and its hops); a rerun skips the rows already there with the same
configuration, so the study can be stopped and resumed. Writes ``robustness_table.md``
(per pair and variant: the median and worst over the copies, worst/best, RICP+NRICP; then
the issue's targets checked) and ``robustness.png``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import resource
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
from morphmodes_vol.variants import VARIANTS, jittered, target_variant  # noqa: E402

QUICK = {"tuning": ["lion-01", "lion-05", "cat-03", "cat-04"],
         "validation": ["dance-04", "jump-03", "chicken-04", "face-03"]}
JITTER = 1e-7
"""The copies' jitter, relative to the source's bounding-box diagonal."""


def decisions(result) -> str:
    """The branches a registration took, from its report: the start kept, each run that
    stopped early and why, the warped pass's choice and hops, the two-way choice."""
    m = result.metrics
    parts = [f"kept {m.get('start', 'rest')}", f"modes {result.modes}"]
    stops = [f"{s['start']}@{s['stopped_after_modes']}:{s['stop_reason']}" for s in m.get("starts", ())
             if s.get("stopped_after_modes") is not None]
    if stops:
        parts.append("stopped " + ", ".join(stops))
    w = m.get("warped_pass")
    if w:
        parts.append(f"warped kept {w.get('kept_before_hops')}")
        for h in w.get("hops", ()):
            parts.append(f"hop {h.get('field', 'field')} {'kept' if h['accepted'] else 'not kept'}")
    if "two_way" in m:
        parts.append(f"two-way kept {m['two_way']['kept']}")
    return "; ".join(parts)


def _limit_memory(gb: float) -> None:
    limit = int(gb * 2**30)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))


def _baseline(source, target, truth) -> dict:
    from morphmodes_vol.baselines import nricp

    t = time.perf_counter()
    r = nricp(source, target, rigid_first=True, ground_truth=truth)
    return {"error": r.metrics["ground_truth_error"], "seconds": time.perf_counter() - t}


def run_baseline(source, target, truth, memory_gb: float) -> dict:
    """RICP+NRICP in a fresh process capped at ``memory_gb``: its error and time, or
    ``status`` "out of memory" (or the error's text)."""
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(1, initializer=_limit_memory, initargs=(memory_gb,)) as pool:
        try:
            return {"status": "ok", **pool.apply(_baseline, (source, target, truth))}
        except MemoryError:
            return {"status": "out of memory", "error": float("nan"), "seconds": float("nan")}
        except Exception as exc:  # noqa: BLE001 - a baseline's failure is a result
            text = f"{type(exc).__name__}: {exc}"
            status = "out of memory" if "memory" in text.lower() or "bad_alloc" in text else text[:200]
            return {"status": status, "error": float("nan"), "seconds": float("nan")}


def run_ours(source, target, truth, options) -> dict:
    t = time.perf_counter()
    try:
        r = mm.register(source, target, options)
    except Exception as exc:  # noqa: BLE001 - a failure is a result of the study
        return {"status": f"{type(exc).__name__}: {exc}"[:200], "error": float("nan"),
                "seconds": time.perf_counter() - t, "decisions": ""}
    return {"status": r.status, "error": ground_truth_error(r.vertices, truth),
            "seconds": time.perf_counter() - t, "decisions": decisions(r)}


# ---------------------------------------------------------------------------- the table
def _summary(rows: list[dict], order: list[str]):
    """Per (pair, variant): the copies' errors of ours and RICP+NRICP's row."""
    ours, base = {}, {}
    for r in rows:
        key = (r["pair"], r["variant"])
        if r["method"] == "ours":
            ours.setdefault(key, []).append(float(r["error"]))
        else:
            base[key] = r
    return ours, base


def table(rows: list[dict], pairs: list[dict], variants: list[str]) -> str:
    ours, base = _summary(rows, [p["pair"] for p in pairs])
    md = ["| set | pair | variant | copies | median | worst | worst/best | RICP+NRICP | RICP+NRICP / median | s per run |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    secs = {}
    for r in rows:
        if r["method"] == "ours":
            secs.setdefault((r["pair"], r["variant"]), []).append(float(r["seconds"]))
    for p in pairs:
        for v in variants:
            e = np.array(ours.get((p["pair"], v), []))
            b = base.get((p["pair"], v))
            if not len(e) and b is None:
                continue
            fin = e[np.isfinite(e)]
            med = float(np.median(e)) if len(e) else float("nan")
            worst = float(np.max(e)) if len(e) else float("nan")
            ratio = worst / fin.min() if len(fin) and fin.min() > 0 else float("nan")
            if b is None:
                bcell, rel = "", ""
            elif b["status"] != "ok":
                bcell, rel = b["status"], ""
            else:
                bcell, rel = f"{float(b['error']):.4f}", f"{float(b['error']) / med:.2f}"
            s = np.mean(secs.get((p["pair"], v), [float("nan")]))
            md.append(f"| {p['set']} | {p['pair']} | {v} | {len(e)} | {med:.4f} | {worst:.4f} | {ratio:.2f} | "
                      f"{bcell} | {rel} | {s:.0f} |")
    md += ["", *targets(rows, pairs, variants)]
    return "\n".join(md) + "\n"


def targets(rows: list[dict], pairs: list[dict], variants: list[str]) -> list[str]:
    """The issue's targets, checked on what the rows hold."""
    ours, base = _summary(rows, [p["pair"] for p in pairs])
    med = {k: float(np.median(v)) for k, v in ours.items()}
    lines = ["Targets (defaults):", ""]
    for s in dict.fromkeys(p["set"] for p in pairs):
        names = [p["pair"] for p in pairs if p["set"] == s]
        orig = [n for n in names if (n, "original") in ours]
        if orig:
            ratios = {n: max(ours[(n, "original")]) / min(ours[(n, "original")]) for n in orig}
            worst = max(ratios, key=ratios.get)
            lines.append(f"- {s}, stability (worst/best over the copies, original target, <= 1.25 on every "
                         f"pair): worst {ratios[worst]:.2f} ({worst}); "
                         f"{sum(r <= 1.25 for r in ratios.values())} of {len(ratios)} pairs within")
        for v in ("retriangulated", "dense"):
            both = [n for n in orig if (n, v) in med]
            if both:
                r = {n: med[(n, v)] / med[(n, "original")] for n in both}
                worst = max(r, key=r.get)
                lines.append(f"- {s}, {v} (median within 1.25x of the original's on every pair): worst "
                             f"{r[worst]:.2f} ({worst}); {sum(x <= 1.25 for x in r.values())} of {len(r)} within")
        for v in variants:
            common = [n for n in names if (n, v) in med and (n, v) in base and base[(n, v)]["status"] == "ok"]
            if not common:
                continue
            m_ours = np.mean([med[(n, v)] for n in common])
            m_base = np.mean([float(base[(n, v)]["error"]) for n in common])
            bar = 5 if v in ("original", "retriangulated", "dense") else 3
            worse = [n for n in common if med[(n, v)] > float(base[(n, v)]["error"])]
            lines.append(f"- {s}, {v}: mean of the medians {m_ours:.4f}, RICP+NRICP {m_base:.4f}: "
                         f"{m_base / m_ours:.2f}x (target {bar}x); worse than RICP+NRICP on "
                         f"{len(worse)} of {len(common)}" + (f" ({', '.join(worse)})" if worse else ""))
    return lines


def plot(rows: list[dict], pairs: list[dict], variants: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ours, base = _summary(rows, [p["pair"] for p in pairs])
    names = [p["pair"] for p in pairs if any((p["pair"], v) in ours for v in variants)]
    fig, ax = plt.subplots(figsize=(max(6, 0.9 * len(names) * len(variants) / 3), 4.5))
    colors = plt.get_cmap("tab10")
    width = 0.8 / len(variants)
    for j, v in enumerate(variants):
        for i, n in enumerate(names):
            x = i + (j - (len(variants) - 1) / 2) * width
            e = ours.get((n, v), [])
            ax.scatter([x] * len(e), e, s=12, color=colors(j), label=v if i == 0 else None, zorder=3)
            b = base.get((n, v))
            if b is not None and b["status"] == "ok":
                ax.scatter([x], [float(b["error"])], marker="_", s=120, color=colors(j), zorder=2)
    ax.set_yscale("log")
    ax.set_xticks(range(len(names)), names, rotation=45, ha="right")
    ax.set_ylabel("ground-truth error (fraction of the diagonal)")
    ax.set_title(f"Robustness: dots = jittered copies (ours), bars = RICP+NRICP")
    ax.legend(fontsize=8, ncol=len(variants))
    ax.grid(True, axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="4 + 4 pairs, K = 3")
    ap.add_argument("--sets", nargs="+", choices=list(SETS), default=list(SETS))
    ap.add_argument("--pairs", nargs="*", default=[], help="only these pairs (e.g. lion-05)")
    ap.add_argument("--copies", type=int, default=None, help="K (default 5, 3 with --quick)")
    ap.add_argument("--variants", nargs="+", choices=VARIANTS, default=[v for v in VARIANTS if v != "no-bridges"])
    ap.add_argument("--methods", nargs="+", choices=["ours", "ricp+nricp"], default=["ours", "ricp+nricp"])
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a RegistrationOptions field of ours (repeatable)")
    ap.add_argument("--baseline-memory-gb", type=float, default=16.0)
    ap.add_argument("--out", default=None, help="output folder (default results/robustness[_quick])")
    ap.add_argument("--plot-only", action="store_true")
    args = ap.parse_args()
    if data_dir() is None:
        ap.error("the shared data is needed (../shared/data or MORPHMODES_DATA)")
    copies = args.copies or (3 if args.quick else 5)
    out = Path(args.out) if args.out else ROOT / "results" / ("robustness_quick" if args.quick else "robustness")
    out.mkdir(parents=True, exist_ok=True)
    csv_path = out / "robustness_runs.csv"
    pairs = plan(args.sets, QUICK if args.quick else None, args.pairs)
    rows = load_rows(out, "robustness_runs") if csv_path.is_file() else []
    options = mm.RegistrationOptions().replace(**parse_overrides(args.set))
    config = {"ours": json.dumps(options.to_dict(), sort_keys=True), "ricp+nricp": "trimesh nricp_amberg defaults"}
    if not args.plot_only:
        done = {(r["pair"], r["variant"], int(r["copy"]), r["method"]) for r in rows
                if r.get("config") == config[r["method"]]}
        rows = [r for r in rows if (r["pair"], r["variant"], int(r["copy"]), r["method"]) in done
                or r["method"] not in args.methods]
        for p in pairs:
            V0, F0 = load_mesh(mesh_file(p["source"]))
            Vt, Ft = load_mesh(mesh_file(p["target"]))
            for v in args.variants:
                target = target_variant(Vt, Ft, v, seed=int(p["pair"][-2:]))
                for method in args.methods:
                    for k in range(copies if method == "ours" else 1):
                        if (p["pair"], v, k, method) in done:
                            continue
                        source = (jittered(V0, JITTER, seed=k), F0)
                        res = (run_ours(source, target, Vt, options) if method == "ours" else
                               run_baseline(source, target, Vt, args.baseline_memory_gb))
                        rows.append({**p, "variant": v, "copy": k, "method": method,
                                     "target_faces": len(target[1]), **res, "config": config[method]})
                        print(f"{p['pair']:>11} {v:>14} copy {k} {method:>10}: {res['error']:.4f} "
                              f"({res['seconds']:.1f} s) {res.get('decisions', res.get('status', ''))}", flush=True)
                        write_csv(csv_path, rows)
        (out / "meta.json").write_text(json.dumps({"command": sys.argv, "copies": copies, "jitter": JITTER,
                                                   "options": json.loads(config["ours"])}, indent=2) + "\n")
    present = [p for p in pairs if any(r["pair"] == p["pair"] for r in rows)]
    text = table(rows, present, args.variants)
    (out / "robustness_table.md").write_text(text)
    if rows:
        plot(rows, present, args.variants, out / "robustness.png")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
