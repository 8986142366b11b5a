"""Accuracy study (issue 5): every lion and cat pose from its reference, plus the perturbation
sweep of experiment 1 on two lion poses, registered by ours (default settings), by the
paper-faithful settings, by NRICP and by RICP+NRICP; ground-truth error and time of each.

    python scripts/accuracy_study.py                       # everything (long: see --methods)
    python scripts/accuracy_study.py --methods nricp ricp+nricp
    python scripts/accuracy_study.py --methods ours --set modes=40 --out results/acc_modes40
    python scripts/accuracy_study.py --plot-only

Pairs: ``lion-reference -> lion-01..09``, ``cat-reference -> cat-01..09``, and the lion
reference rotated about its forward axis (z) through its box center by ``--angles`` degrees
onto ``--sweep-targets`` (default lion-01 and lion-05). Ground-truth error:
``mean_i ||registered_i - pose_i|| / bbox_diagonal(pose)`` (shared/data README).

Methods:
- ``ours``: :class:`morphmodes_vol.RegistrationOptions` defaults, with ``--set`` overrides;
- ``fast``: the ``fast`` preset (grid 48, the band quadrature,
  no warped-pass starts from the other orientations), with the same overrides;
- ``fastest``: the ``fastest`` preset (the warped rest field alone from the
  rest pose and the SDF alignment, refined on Eq. 3; no runs of Algorithm 1), with the same
  overrides;
- ``no-warped``: the defaults with ``warped_pass=False`` (the runs alone, without the warped
  rest field);
- ``two-way``: the ``accurate`` preset, the defaults with ``two_way=True`` (the reverse
  registration's correspondences as two more starts; 1.7-2.4x the time);
- ``paper``: the paper-faithful settings, :meth:`RegistrationOptions.paper_faithful`
  (Algorithm 1's gradient descent from the rest pose, no initialization stage, 20 modes),
  at ``--paper-grid`` (default 64, the default grid; the paper's optimizer takes 3-6 min per
  pair there, so the whole column takes about two hours on 2 cores);
- ``nricp``, ``ricp+nricp``: trimesh ``nricp_amberg`` with its default schedule, alone and
  after rigid ICP (:mod:`morphmodes_vol.baselines`).

Runs are appended to ``<out>/accuracy_runs.csv`` as they finish; a rerun skips the
(pair, method) rows already there with the same configuration, so the study can be stopped
and resumed, and columns can be filled by separate invocations. ``--redo METHOD`` drops a
method's rows first.

Writes ``<out>/accuracy_runs.csv``, ``accuracy_table.md`` (error and time of every method per
pair, the means and the ratios RICP+NRICP / ours, / fast, / no-warped and / two-way) and
``accuracy.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _data import ROOT, parse_overrides, write_csv  # noqa: E402
from _exp import load_rows, mesh_path, rotated_source  # noqa: E402

import morphmodes_vol as mm  # noqa: E402
from morphmodes_vol.baselines import nricp, prepare_pair  # noqa: E402
from morphmodes_vol.mesh import load_mesh  # noqa: E402

METHODS = ("ours", "fast", "fastest", "no-warped", "two-way", "paper", "nricp", "ricp+nricp")
OURS = ("ours", "fast", "fastest", "no-warped", "two-way")  # our settings compared with RICP+NRICP pair by pair


#: options added with a default other than the earlier behaviour: a row stored before the
#: option existed ran with this value
CHANGED_DEFAULTS = {"warped_pass": False, "warped_candidates": False, "warped_prune_modes": 0, "warped_hops": 0, "warped_descriptors": False}


def same_config(stored: str | None, current: str) -> bool:
    """Whether a row's stored configuration is the current one: equal, or equal but for
    options added to :class:`RegistrationOptions` since, at the values that keep the earlier
    behaviour (their defaults, or :data:`CHANGED_DEFAULTS`), so rows survive new options."""
    if stored == current:
        return True
    if not (stored or "").startswith("{") or not current.startswith("{"):
        return False
    old, new = json.loads(stored), json.loads(current)
    before = {**mm.RegistrationOptions().to_dict(), **CHANGED_DEFAULTS}
    return (set(old) <= set(new) and all(old[k] == new[k] for k in old)
            and all(new[k] == before[k] for k in set(new) - set(old)))


def pairs(angles: list[float], sweep_targets: list[str]) -> list[dict]:
    """Every pair of the study: name, source, target and rotation angle of the source."""
    out = []
    for animal in ("lion", "cat"):
        for i in range(1, 10):
            out.append({"pair": f"{animal}-{i:02d}", "source": f"{animal}-reference",
                        "target": f"{animal}-{i:02d}", "angle": 0.0})
    for target in sweep_targets:
        for a in angles:
            if a == 0:
                continue  # the unrotated pair is already in the pose list
            out.append({"pair": f"{target} rot {a:+.0f}", "source": "lion-reference",
                        "target": target, "angle": float(a)})
    return out


def run_method(method: str, source, target, truth, options: "mm.RegistrationOptions") -> dict:
    t = time.perf_counter()
    if method in OURS + ("paper",):
        r = mm.register(source, target, options, ground_truth=truth)
        extra = {"evaluations": r.evaluations, "modes": r.modes, "status": r.status,
                 "start": r.metrics.get("start", "rest"), "edge_strain": r.metrics.get("edge_strain", "")}
    else:
        r = nricp(source, target, rigid_first=method == "ricp+nricp", ground_truth=truth,
                  pair=prepare_pair(source, target, options))
        extra = {"evaluations": "", "modes": "", "status": r.status, "start": "", "edge_strain": ""}
    return {"identity_error": r.metrics["identity_error"], "error": r.metrics["ground_truth_error"],
            "seconds": time.perf_counter() - t, **extra}


def table(rows: list[dict], order: list[str]) -> str:
    """Markdown: one line per pair, error and time of every method, and the summary lines."""
    methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
    by = {(r["pair"], r["method"]): r for r in rows}
    head = "| pair | identity | " + " | ".join(f"{m} error | {m} s" for m in methods)
    ours = [m for m in OURS if m in methods and "ricp+nricp" in methods]
    md = [head + "".join(f" | RICP+NRICP / {m}" for m in ours) + " |",
          "|---|---|" + "---|---|" * len(methods) + "---|" * len(ours)]
    for p in order:
        cells = [by.get((p, m)) for m in methods]
        if not any(cells):
            continue
        ident = next(c for c in cells if c)["identity_error"]
        line = f"| {p} | {ident:.4f} | " + " | ".join(
            f"{c['error']:.4f} | {c['seconds']:.0f}" if c else " | " for c in cells)
        for m in ours:
            o, b = by.get((p, m)), by.get((p, "ricp+nricp"))
            line += f" | {b['error'] / o['error']:.2f}" if o and b else " | "
        md.append(line + " |")
    # summary over the pairs every method has
    common = [p for p in order if all((p, m) in by for m in methods)]
    if common:
        mean = {m: np.mean([by[(p, m)]["error"] for p in common]) for m in methods}
        secs = {m: np.mean([by[(p, m)]["seconds"] for p in common]) for m in methods}
        line = f"| **mean over {len(common)} pairs** | | " + " | ".join(
            f"**{mean[m]:.4f}** | {secs[m]:.0f}" for m in methods)
        line += "".join(f" | **{mean['ricp+nricp'] / mean[m]:.2f}**" for m in ours)
        md.append(line + " |")
        for m in ours:
            worse = [p for p in common if by[(p, m)]["error"] > by[(p, "ricp+nricp")]["error"]]
            md.append("")
            md.append(f"{'Ours' if m == 'ours' else f'Ours, {m},'} worse than RICP+NRICP on "
                      f"{len(worse)} of {len(common)} pairs" + (f": {', '.join(worse)}." if worse else "."))
    return "\n".join(md) + "\n"


def plot(rows: list[dict], order: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
    by = {(r["pair"], r["method"]): r["error"] for r in rows}
    ident = {r["pair"]: r["identity_error"] for r in rows}
    present = [p for p in order if p in ident]
    x = np.arange(len(present))
    fig, ax = plt.subplots(figsize=(max(8, 0.38 * len(present)), 3.8))
    ax.plot(x, [ident[p] for p in present], "k:", label="identity", lw=1)
    for m, style in zip(METHODS, ("s-", "x-", "P-", "v-", "d--", "^-.", "o--")):
        if m in methods:
            ax.plot(x, [by.get((p, m), np.nan) for p in present], style, label=m, ms=4)
    ax.set_xticks(x)
    ax.set_xticklabels(present, rotation=70, fontsize=7)
    ax.set_ylabel("ground-truth error / target diagonal")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    ap.add_argument("--pairs", nargs="*", default=None,
                    help="only these pairs (names as in the table, e.g. lion-05 'lion-01 rot +30')")
    ap.add_argument("--angles", type=float, nargs="+", default=[-30, -20, -10, 0, 10, 20, 30])
    ap.add_argument("--sweep-targets", nargs="*", default=["lion-01", "lion-05"])
    ap.add_argument("--set", nargs="*", default=[], metavar="OPTION=VALUE",
                    help="override the options of 'ours', 'fast', 'fastest', 'no-warped' and 'two-way', "
                         "e.g. --set modes=40")
    ap.add_argument("--paper-grid", type=int, default=64, help="quadrature grid of 'paper'")
    ap.add_argument("--redo", nargs="*", default=[], choices=METHODS, help="drop these methods' rows first")
    ap.add_argument("--out", default=str(ROOT / "results" / "accuracy_study"))
    ap.add_argument("--plot-only", action="store_true", help="redraw the table and plot from the CSV")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    csv_path = out / "accuracy_runs.csv"
    plan = pairs(args.angles, args.sweep_targets)
    order = [p["pair"] for p in plan]
    rows = load_rows(out, "accuracy_runs") if csv_path.is_file() else []
    rows = [r for r in rows if r["method"] not in args.redo]

    settings = {
        "ours": mm.RegistrationOptions,
        "fast": mm.RegistrationOptions.fast,
        "fastest": mm.RegistrationOptions.fastest,
        "no-warped": lambda: mm.RegistrationOptions(warped_pass=False),
        "two-way": lambda: mm.RegistrationOptions.preset("accurate"),
    }
    configs = {
        "paper": mm.RegistrationOptions.paper_faithful().replace(grid=args.paper_grid),
        "nricp": mm.RegistrationOptions(),  # grid for the SDF residual metric only
        "ricp+nricp": mm.RegistrationOptions(),
    }
    for m, make in settings.items():
        try:
            configs[m] = make().replace(**parse_overrides(args.set))
        except mm.OptionError as exc:  # an override that one of our settings cannot take
            if m in args.methods:
                ap.error(f"--set for {m!r}: {exc}")
            configs[m] = None  # not run now: its stored rows stay as they are
    config_key = {m: json.dumps(o.to_dict(), sort_keys=True) if o is not None else "" for m, o in configs.items()}
    for m in ("nricp", "ricp+nricp"):
        config_key[m] = "trimesh nricp_amberg defaults"
    if not args.plot_only:
        done = {(r["pair"], r["method"]) for r in rows if same_config(r.get("config"), config_key[r["method"]])}
        # the methods run now redo their rows of other configurations; other methods' rows stay
        rows = [r for r in rows if r["method"] not in args.methods or (r["pair"], r["method"]) in done]
        cache: dict[str, tuple] = {}
        for p in plan:
            if args.pairs and p["pair"] not in args.pairs:
                continue
            for method in args.methods:
                if (p["pair"], method) in done:
                    continue
                if p["source"] not in cache:
                    cache[p["source"]] = load_mesh(mesh_path(p["source"]))
                V0, F = cache[p["source"]]
                target = mesh_path(p["target"])
                truth = load_mesh(target)[0]
                # turned about z, the lion's forward axis (the unturned poses as loaded)
                V = rotated_source(V0, 2, p["angle"]) if p["angle"] else V0
                res = run_method(method, (V, F), target, truth, configs[method])
                rows.append({**p, "method": method, **res, "config": config_key[method]})
                print(f"{p['pair']:>16} {method:>10}: identity {res['identity_error']:.4f} -> "
                      f"{res['error']:.4f} ({res['seconds']:.1f} s)", flush=True)
                write_csv(csv_path, rows)
        (out / "meta.json").write_text(json.dumps(
            {"command": sys.argv, "configs": {m: json.loads(k) if k.startswith("{") else k
                                              for m, k in config_key.items()}}, indent=2) + "\n")
    text = table(rows, order)
    (out / "accuracy_table.md").write_text(text)
    if rows:
        plot(rows, order, out / "accuracy.png")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
