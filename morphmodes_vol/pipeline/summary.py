"""The summary of a run, rebuilt from the per-pair folders: CSV, JSON, a markdown table and a
PNG plot of the error per pair (the plot needs matplotlib and is skipped without it)."""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from pathlib import Path

from ..export import atomic_write_bytes
from .definition import Pipeline, PairSpec

__all__ = ["pair_row", "write_summary", "markdown_table", "COLUMNS"]

log = logging.getLogger(__name__)

COLUMNS = ("pair", "variant", "state", "status", "identity_error", "ground_truth_error", "ratio",
           "final_sdf_rms", "modes", "evaluations", "seconds", "eigenbasis_cached",
           "target_sdf_cached", "error", "source", "target")


def _variant(spec: PairSpec) -> str:
    return " ".join(f"{k}={v}" for k, v in spec.variant.items())


def pair_row(spec: PairSpec, result: dict) -> dict:
    """One summary row from the pair's folder (``report.json`` or ``failed.json``)."""
    row = dict.fromkeys(COLUMNS)
    row.update(pair=spec.name, variant=_variant(spec), source=str(spec.source), target=str(spec.target),
               state=result["state"], seconds=result.get("seconds"))
    if result["state"] in ("ok", "skipped"):
        try:
            report = json.loads((spec.outdir / "report.json").read_text())
        except (OSError, ValueError) as exc:
            row.update(state="failed", error=f"report.json unreadable after the run ({exc})")
            return row
        m = report["metrics"]
        info = report["inputs"]["pipeline"]
        row.update(status=report["status"], final_sdf_rms=m["final_sdf_rms"], modes=report["modes"],
                   evaluations=report["evaluations"], seconds=info["seconds"],
                   eigenbasis_cached=info["products"]["eigenbasis"]["cached"],
                   target_sdf_cached=info["products"]["target_sdf"]["cached"])
        if "ground_truth_error" in m:
            row.update(identity_error=m["identity_error"], ground_truth_error=m["ground_truth_error"],
                       ratio=m["ground_truth_error"] / m["identity_error"] if m["identity_error"] else None)
    else:
        row["error"] = result.get("error")
    return row


def _fmt(value, digits: int = 4) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value).replace("|", "\\|")


def _mean(rows: list[dict], key: str):
    values = [r[key] for r in rows if isinstance(r.get(key), (int, float)) and not isinstance(r.get(key), bool)]
    return sum(values) / len(values) if values else None


def markdown_table(rows: list[dict]) -> str:
    """The summary as a markdown table with a mean row over the successful pairs.

    Examples
    --------
    >>> print(markdown_table([{"pair": "a__b", "variant": "", "state": "ok", "status": "converged",
    ...     "identity_error": 0.2, "ground_truth_error": 0.05, "ratio": 0.25, "final_sdf_rms": 0.001,
    ...     "modes": 3, "evaluations": 90, "seconds": 4.0, "error": None}]).splitlines()[2])
    | a__b |  | ok | converged | 0.2000 | 0.0500 | 0.25 | 0.0010 | 3 | 90 | 4.0 |  |
    """
    head = ("| pair | variant | state | status | identity error | registered error | ratio | "
            "final SDF RMS | modes | SDF evaluations | wall time (s) | error |")
    lines = [head, "|" + "---|" * head.count(" | ") + "---|"]
    for r in rows:
        lines.append("| " + " | ".join([
            _fmt(r["pair"]), _fmt(r["variant"]), _fmt(r["state"]), _fmt(r["status"]),
            _fmt(r["identity_error"]), _fmt(r["ground_truth_error"]), _fmt(r["ratio"], 2),
            _fmt(r["final_sdf_rms"]), _fmt(r["modes"]), _fmt(r["evaluations"]),
            _fmt(r["seconds"], 1), _fmt(r["error"]),
        ]) + " |")
    ok = [r for r in rows if r["state"] in ("ok", "skipped")]
    if len(ok) > 1:
        lines.append("| **mean** | | | | " + " | ".join([
            _fmt(_mean(ok, "identity_error")), _fmt(_mean(ok, "ground_truth_error")), _fmt(_mean(ok, "ratio"), 2),
            _fmt(_mean(ok, "final_sdf_rms")), "", "", _fmt(_mean(ok, "seconds"), 1), "",
        ]) + " |")
    return "\n".join(lines) + "\n"


def _plot(rows: list[dict], metric: str, title: str) -> bytes | None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        log.warning("matplotlib is not installed: no summary.png (pip install matplotlib)")
        return None
    if metric not in COLUMNS:
        metric = "final_sdf_rms"
    if metric == "ground_truth_error" and all(r.get(metric) is None for r in rows):
        metric = "final_sdf_rms"
    names = [r["pair"] for r in rows]
    values = [r.get(metric) if r.get(metric) is not None else math.nan for r in rows]
    fig, ax = plt.subplots(figsize=(max(6.0, 0.45 * len(rows) + 2), 4.0))
    x = range(len(rows))
    if metric == "ground_truth_error":
        ident = [r["identity_error"] if r.get("identity_error") is not None else math.nan for r in rows]
        ax.bar([i - 0.2 for i in x], ident, width=0.4, label="identity", color="0.7")
        ax.bar([i + 0.2 for i in x], values, width=0.4, label="registered", color="C0")
        ax.legend()
    else:
        ax.bar(list(x), values, color="C0")
    for i, r in enumerate(rows):
        if r["state"] == "failed":
            ax.text(i, 0, "failed", rotation=90, ha="center", va="bottom", color="C3")
    ax.set_xticks(list(x))
    ax.set_xticklabels(names, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel(metric.replace("_", " "))
    ax.set_title(title)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


def write_summary(pipeline: Pipeline, results: list[dict], run_info: dict) -> tuple[list[dict], dict[str, Path]]:
    """Write ``summary.{csv,json,md,png}`` in ``pipeline.output``; return the rows and paths."""
    by_name = {r["name"]: r for r in results}
    rows = [pair_row(spec, by_name[spec.name]) for spec in pipeline.pairs if spec.name in by_name]
    out = pipeline.output
    paths = {k: out / f"summary.{k}" for k in ("csv", "json", "md", "png")}
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(COLUMNS))
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_bytes(paths["csv"], buf.getvalue().encode())
    doc = {"pipeline": pipeline.name, "definition": str(pipeline.path), **run_info, "pairs": rows}
    atomic_write_bytes(paths["json"], (json.dumps(doc, indent=2) + "\n").encode())
    atomic_write_bytes(paths["md"], markdown_table(rows).encode())
    png = _plot(rows, pipeline.plot_metric, pipeline.name)
    if png is None:
        del paths["png"]
    else:
        atomic_write_bytes(paths["png"], png)
    return rows, paths
