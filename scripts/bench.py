"""Speed benchmark: ours (the default settings; one
Levenberg-Marquardt run from the rest pose (``--methods lm``); and ``--preset paper``, the paper-faithful
settings) against trimesh's non-rigid ICP (Amberg et al. 2007, ``trimesh.registration.nricp_amberg`` with its defaults),
in one run, on the same machine; with ``--methods``, also the fast and fastest settings
(``fast``, ``fastest``) and others.

    python scripts/bench.py [--pairs 05 01] [--out results/bench] [--set grid=64 ...]
    python scripts/bench.py --targets-only --out DIR   # the targets of a run already in DIR
    make bench

Pairs: lion-reference onto lion-05 and lion-01 from ``../shared/data`` (or
``$MORPHMODES_DATA``); without the data, a generated capsule onto a bent, stretched copy.
Every method runs in a fresh child process, one after the other (never two at once), so its
wall time and peak resident memory are its own. Wall time covers everything from file paths
to written results: loading, preprocessing, target SDF, eigenbasis, optimization and export
for ours; loading and the registration call for NRICP. The libraries each method uses are
imported before its clock starts (``_import_libraries``; Open3D's import alone takes about
0.4 s here): a per-process cost, paid once by a script that registers many pairs.

Prints a markdown table, then where each pair stands against the issue-6 targets the run
can measure (:func:`targets`: the default's wall time against a third of NRICP's, and its
full-grid equivalents against a tenth of the paper-faithful optimizer's at no higher error),
and writes ``<out>/bench.json`` and ``<out>/bench.md``.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import json
import multiprocessing as mp
import platform
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _data import ROOT, data_dir, parse_overrides  # noqa: E402


def _peak_rss_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _load(path_or_pair):
    import morphmodes_vol as mm

    if isinstance(path_or_pair, tuple):
        return path_or_pair
    return mm.as_mesh(path_or_pair, str(path_or_pair))


def _import_libraries(method: str) -> None:
    """Import the libraries ``method`` (``"ours"`` or ``"nricp"``) uses, before its clock
    starts: ours imports Open3D and libigl lazily, NRICP lives in ``trimesh.registration``.
    Only these, so that each method's peak memory holds only its own libraries."""
    import scipy.sparse.linalg  # noqa: F401

    if method == "ours":
        import igl  # noqa: F401
        import open3d  # noqa: F401
    else:
        import trimesh.registration  # noqa: F401


def run_ours(source, target, truth, overrides: dict, preset: str = "default") -> dict:
    """One registration with our method, timed stage by stage (runs in a child process):
    ``RegistrationOptions()`` (``preset="default"``), ``fast()`` (``"fast"``), ``fastest()``
    (``"fastest"``) or ``paper_faithful()`` (``"paper"``) with ``overrides``."""
    import numpy as np

    import morphmodes_vol as mm

    _import_libraries("ours")
    t0 = time.perf_counter()
    options = mm.RegistrationOptions.preset(preset).replace(**overrides)
    reg = mm.Registration(_load(source), _load(target), options)
    result = reg.run()
    t = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        mm.write_outputs(result, tmp)
    export = time.perf_counter() - t
    wall = time.perf_counter() - t0
    truth_V = np.asarray(_load(truth)[0])
    h = result.history
    timings = dict(result.timings)
    timings["export"] = export
    evaluations = result.evaluations  # every start's
    return {
        "wall_s": wall,
        "error": mm.ground_truth_error(result.vertices, truth_V),
        "identity_error": mm.ground_truth_error(reg.source_vertices, truth_V),
        "evaluations": evaluations,
        # on the coarse pass's grid (every other node), each a few times cheaper
        "coarse_evaluations": result.metrics.get("coarse_evaluations_all_starts", 0),
        "init_evaluations": result.metrics.get("init_evaluations", 0),
        # the objectives that compared runs, not in "evaluations"
        "comparison_evaluations": result.metrics.get("comparison_evaluations", 0),
        # points sent to the source's closest-point queries, over the grid's nodes: the cost
        # in evaluations on the full grid (each of --preset paper's is one)
        "full_grid_equivalents": result.metrics.get("full_grid_equivalents"),
        "start": result.metrics.get("start", "rest"),
        "steps": len(h.step_rms),
        "modes": result.modes,
        "status": result.status,
        "seconds_per_evaluation": timings["sdf_queries"] / max(
            evaluations + result.metrics.get("comparison_evaluations", 0), 1),
        "sdf_share_of_optimize": timings["sdf_queries"] / max(timings["optimize"], 1e-12),
        "timings": timings,
        "peak_rss_mb": _peak_rss_mb(),
        "options": options.to_dict(),
    }


def run_nricp(source, target, truth) -> dict:
    """trimesh's ``nricp_amberg`` with its defaults (runs in a child process)."""
    import numpy as np
    import trimesh

    import morphmodes_vol as mm

    _import_libraries("nricp")
    t0 = time.perf_counter()
    V, F = _load(source)
    TV, TF = _load(target)
    out = trimesh.registration.nricp_amberg(
        trimesh.Trimesh(V, F, process=False), trimesh.Trimesh(TV, TF, process=False)
    )
    wall = time.perf_counter() - t0
    truth_V = np.asarray(_load(truth)[0])
    return {
        "wall_s": wall,
        "error": mm.ground_truth_error(np.asarray(out), truth_V),
        "identity_error": mm.ground_truth_error(V, truth_V),
        "peak_rss_mb": _peak_rss_mb(),
    }


def _in_child(fn, *args) -> dict:
    """Run ``fn(*args)`` in a fresh process (spawned: no state shared with earlier runs)."""
    with cf.ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn")) as ex:
        return ex.submit(fn, *args).result()


def pairs(selected: list[str]) -> list[tuple[str, object, object]]:
    """``(name, source, target)``; target is also the ground truth (same vertex order)."""
    data = data_dir()
    if data is None:
        from morphmodes_vol.demo import demo_pair

        source, target = demo_pair()
        return [("capsule -> bent capsule (generated)", source, target)]
    lion = data / "lion-poses"
    return [(f"lion-reference -> lion-{p}", lion / "lion-reference.obj", lion / f"lion-{p}.obj")
            for p in selected]


def _row(pair: str, method: str, r: dict, nricp_wall: float | None) -> str:
    ratio = f"{r['wall_s'] / nricp_wall:.2f}" if nricp_wall else ""
    ev = r.get("evaluations", "")
    notes = [f"{r[k]} {name}" for k, name in (("coarse_evaluations", "coarse"),) if r.get(k)]
    if notes:
        ev = f"{ev} ({', '.join(notes)})"
    if r.get("comparison_evaluations"):
        k = r["comparison_evaluations"]
        ev = f"{ev} + {k} comparison{'s' if k > 1 else ''}"
    equivalents = f"{r['full_grid_equivalents']:.1f}" if r.get("full_grid_equivalents") is not None else ""
    spe = f"{1000 * r['seconds_per_evaluation']:.0f}" if "seconds_per_evaluation" in r else ""
    share = f"{100 * r['sdf_share_of_optimize']:.0f}%" if "sdf_share_of_optimize" in r else ""
    stages = ""
    if "timings" in r:
        t = r["timings"]
        stages = " / ".join(f"{t[k]:.1f}" for k in
                            ("preprocess", "target_sdf", "eigenbasis", "initialize", "optimize", "export"))
    return (f"| {pair} | {method} | {r['identity_error']:.4f} | {r['error']:.4f} | "
            f"{r['wall_s']:.1f} | {ratio} | {ev} | {equivalents} | {spe} | {share} | {stages} | "
            f"{r['peak_rss_mb']:.0f} |")


TIME_RATIO = 1.0 / 3.0  # issue 6: the default's wall time at most a third of NRICP's
EVALUATION_FACTOR = 10.0  # issue 6: at least 10x fewer full evaluations than the paper's optimizer


def targets(results: dict) -> dict:
    """Where one pair's run stands against the issue-6 targets it can measure.

    Parameters
    ----------
    results : dict
        Method label (``"ours, default"``, ``"ours, --preset paper"``, ``"trimesh
        nricp_amberg"``) -> its result (``wall_s``, ``error``, ``full_grid_equivalents``).

    Returns
    -------
    dict
        ``"wall_time"``: the default's wall time over NRICP's (``ratio``), ``met`` when at
        most :data:`TIME_RATIO` and its error is no higher than the paper-faithful
        optimizer's (when that ran; the target asks both); ``"evaluations"``: the paper's
        full-grid equivalents over the default's (``factor``), ``met`` when at least
        :data:`EVALUATION_FACTOR` at no higher error. A target whose methods did not run is
        left out. ``"settings"``: the same wall-time ratio for ``--preset fast`` and ``--preset fastest`` when
        they ran (``ratio``, ``error``; not targets: the targets are of the defaults).

    Examples
    --------
    >>> t = targets({"ours, default": {"wall_s": 3.0, "error": 0.01, "full_grid_equivalents": 40.0},
    ...              "trimesh nricp_amberg": {"wall_s": 9.0, "error": 0.2},
    ...              "ours, --preset paper": {"wall_s": 300.0, "error": 0.3, "full_grid_equivalents": 400.0}})
    >>> t["wall_time"]["met"], t["evaluations"]["factor"], t["evaluations"]["met"]
    (True, 10.0, True)
    """
    ours, nricp = results.get("ours, default"), results.get("trimesh nricp_amberg")
    paper = results.get("ours, --preset paper")
    out = {}
    no_worse = paper is None or ours is None or ours["error"] <= paper["error"]
    if ours and nricp:
        ratio = ours["wall_s"] / nricp["wall_s"]
        out["wall_time"] = {"ratio": ratio, "target": TIME_RATIO, "met": bool(ratio <= TIME_RATIO and no_worse)}
    others = {label: results[f"ours, {label}"] for label in ("--preset fast", "--preset fastest") if f"ours, {label}" in results}
    if nricp and others:
        out["settings"] = {label: {"ratio": r["wall_s"] / nricp["wall_s"], "error": r["error"]}
                           for label, r in others.items()}
    if ours and paper and ours.get("full_grid_equivalents") and paper.get("full_grid_equivalents"):
        factor = paper["full_grid_equivalents"] / ours["full_grid_equivalents"]
        out["evaluations"] = {"factor": factor, "target": EVALUATION_FACTOR,
                              "met": bool(factor >= EVALUATION_FACTOR and no_worse)}
    return out


def target_line(pair: str, t: dict, results: dict, overrides: dict | None = None) -> str | None:
    parts = []
    ours, paper = results.get("ours, default"), results.get("ours, --preset paper")
    if "wall_time" in t:
        w = t["wall_time"]
        parts.append(f"wall time {w['ratio']:.2f}x NRICP's (at most {w['target']:.2f}x): "
                     f"**{'met' if w['met'] else 'not met'}**")
    if "evaluations" in t:
        e = t["evaluations"]
        parts.append(f"full-grid equivalents {ours['full_grid_equivalents']:.1f} against the paper-faithful "
                     f"optimizer's {paper['full_grid_equivalents']:.1f}, {e['factor']:.1f}x fewer (at least "
                     f"{e['target']:.0f}x), error {ours['error']:.4f} against {paper['error']:.4f}: "
                     f"**{'met' if e['met'] else 'not met'}**")
    if "settings" in t:  # the other settings' ratios, for comparison (also without the default)
        parts.append(("" if parts else "the default did not run; ") + "the other settings: " + ", ".join(
            f"{label} {v['ratio']:.2f}x at error {v['error']:.4f}" for label, v in t["settings"].items()))
    if parts and overrides:  # the targets are of the default settings
        parts.append("ours ran with --set " + " ".join(f"{k}={v}" for k, v in overrides.items())
                     + ", not the default settings")
    return f"- issue-6 targets, {pair}: " + "; ".join(parts) if parts else None


def add_targets(report: dict, pair: str, results: dict, lines: list[str]) -> None:
    """One pair's :func:`targets`, into ``report["targets"]`` and, as a line, onto ``lines``
    (nothing when no target's methods ran)."""
    t = targets(results)
    if t:
        report.setdefault("targets", {})[pair] = t
        line = target_line(pair, t, results, report.get("overrides"))
        if line is not None:
            lines.append(line)


def _targets_only(out: Path) -> int:
    """``--targets-only``: the target lines of the run saved in ``out``, without running it
    again (the table of ``bench.md`` is kept; target lines already there are replaced)."""
    path = out / "bench.json"
    if not path.is_file():
        print(f"no benchmark in {out}: {path} is missing", file=sys.stderr)
        return 2
    report = json.loads(path.read_text())
    by_pair: dict = {}
    for r in report["results"]:
        by_pair.setdefault(r["pair"], {})[r["method"]] = r
    report["targets"], target_lines = {}, []
    for pair, results in by_pair.items():
        add_targets(report, pair, results, target_lines)
    print("\n".join(target_lines) if target_lines else "no pair ran the methods a target compares")
    path.write_text(json.dumps(report, indent=2, default=str))
    md = out / "bench.md"
    table = [line for line in (md.read_text().splitlines() if md.is_file() else [])
             if not line.startswith("- issue-6 targets")]
    while table and not table[-1]:
        table.pop()
    md.write_text("\n".join(table + ([""] + target_lines if target_lines else [])) + "\n")
    return 0


HEADER = ("| pair | method | identity error | error | wall s | / NRICP | SDF evals | full-grid equivalents "
          "| ms / eval | SDF share | preprocess / target SDF / eigenbasis / initialize / optimize / export (s) "
          "| peak RSS MB |\n|---|---|---|---|---|---|---|---|---|---|---|---|")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pairs", nargs="*", default=["05", "01"], help="lion poses")
    ap.add_argument("--out", default=str(ROOT / "results" / "bench"))
    ap.add_argument("--set", nargs="*", default=[], metavar="OPTION=VALUE",
                    help="override options of every run of ours, e.g. --set grid=48")
    ap.add_argument("--methods", nargs="*", default=["default", "lm", "paper", "nricp"],
                    choices=["default", "accurate", "fast", "fastest", "no-descriptors", "no-warped", "lm",
                             "paper", "nricp"],
                    help="default, accurate, fast, fastest, paper: the presets; no-descriptors, no-warped: "
                         "the defaults with warped_descriptors=false, warped_pass=false (not "
                         "run unless named); lm: one run from the rest pose (initialization=none, "
                         "coarse_starts=false, warped_pass=false); nricp: trimesh")
    ap.add_argument("--docs", action="store_true",
                    help="also write the table to docs/benchmarks.md (the project's current benchmark)")
    ap.add_argument("--targets-only", action="store_true",
                    help="run nothing: read <out>/bench.json, print where each pair stands against the "
                         "issue-6 targets and add it to it and to <out>/bench.md")
    args = ap.parse_args()
    if args.targets_only:
        return _targets_only(Path(args.out))
    overrides = parse_overrides(args.set)

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = {"machine": {"python": platform.python_version(), "cpus": mp.cpu_count(),
                          "platform": platform.platform()},
              "overrides": overrides, "results": []}
    lines, target_lines = [HEADER], []
    print(HEADER, flush=True)
    for name, source, target in pairs(args.pairs):
        results = {}
        if "nricp" in args.methods:
            results["trimesh nricp_amberg"] = _in_child(run_nricp, source, target, target)
        if "default" in args.methods:
            results["ours, default"] = _in_child(run_ours, source, target, target, overrides)
        if "fast" in args.methods:  # RegistrationOptions.fast()
            results["ours, --preset fast"] = _in_child(run_ours, source, target, target, overrides, "fast")
        if "fastest" in args.methods:  # RegistrationOptions.fastest()
            results["ours, --preset fastest"] = _in_child(run_ours, source, target, target, overrides, "fastest")
        if "no-descriptors" in args.methods:
            results["ours, --set warped_descriptors=false"] = _in_child(run_ours, source, target, target,
                                                                 {"warped_descriptors": False, **overrides})
        if "no-warped" in args.methods:
            results["ours, --set warped_pass=false"] = _in_child(run_ours, source, target, target,
                                                          {"warped_pass": False, **overrides})
        if "accurate" in args.methods:  # the defaults and two-way
            results["ours, --preset accurate"] = _in_child(run_ours, source, target, target, overrides, "accurate")
        if "lm" in args.methods:  # the fast path before the initialization stage: one run
            results["ours, one run from the rest pose"] = _in_child(
                run_ours, source, target, target,
                {"initialization": "none", "coarse_starts": False, "warped_pass": False, **overrides})
        if "paper" in args.methods:  # the paper-faithful settings
            results["ours, --preset paper"] = _in_child(
                run_ours, source, target, target, overrides, "paper")
        nricp_wall = results.get("trimesh nricp_amberg", {}).get("wall_s")
        for method, r in results.items():
            line = _row(name, method, r, nricp_wall)
            lines.append(line)
            print(line, flush=True)
            report["results"].append({"pair": name, "method": method, **r})
        add_targets(report, name, results, target_lines)
    if target_lines:
        print("\n" + "\n".join(target_lines), flush=True)
        lines += [""] + target_lines
    (out / "bench.json").write_text(json.dumps(report, indent=2, default=str))
    (out / "bench.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / 'bench.json'} and {out / 'bench.md'}")
    if args.docs:
        docs = ROOT / "docs" / "benchmarks.md"
        docs.write_text(benchmarks_page(lines, args, report["machine"]))
        print(f"wrote {docs}")
    return 0


def benchmarks_page(lines: list[str], args, machine: dict) -> str:
    """docs/benchmarks.md: the table of a run (``lines``), the command that made it (from
    its parsed ``args``, without the machine's output folder) and the machine."""
    command = " ".join(["python scripts/bench.py", "--pairs", *args.pairs, "--methods", *args.methods,
                        *(["--set", *args.set] if args.set else []), "--docs"])
    return (f"# Benchmark\n\nWritten by `{command}` on "
            f"{time.strftime('%Y-%m-%d')}, {machine['cpus']} CPUs, Python {machine['python']} "
            f"({machine['platform']}). Every method runs in a child process of its own, one after "
            "the other; wall time covers loading to written results. Compare ratios within a "
            "table: NRICP's own time varies from machine to machine.\n\n" + "\n".join(lines) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
