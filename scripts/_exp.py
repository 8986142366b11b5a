"""Helpers shared by the experiment scripts (exp*.py): data paths, option overrides,
tables (CSV + markdown), saved meshes, rotations and the common metric columns."""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import numpy as np

from _data import ROOT, data_dir, parse_overrides, write_csv

import morphmodes_vol as mm

METRIC_COLUMNS = [
    ("ground_truth_error", "GT error", "{:.4f}"),
    ("surface_mean", "surface mean", "{:.4f}"),
    ("surface_hausdorff", "Hausdorff", "{:.3f}"),
    ("final_sdf_rms", "SDF RMS", "{:.4f}"),
    ("collapsed_fraction", "collapsed", "{:.3%}"),
    ("flipped_fraction", "flipped", "{:.3%}"),
    ("volume_ratio", "volume ratio", "{:.3f}"),
    ("seconds", "time (s)", "{:.0f}"),
]


def mesh_path(name: str) -> Path:
    """``"lion-01"`` -> ``<data>/lion-poses/lion-01.obj`` (``cat-*`` likewise)."""
    data = data_dir()
    if data is None:
        sys.exit("shared data not found (set MORPHMODES_DATA)")
    path = data / f"{name.split('-')[0]}-poses" / f"{name}.obj"
    if not path.is_file():
        sys.exit(f"{path}: no such mesh")
    return path


def out_dir(default: str, given: str | None) -> Path:
    out = Path(given) if given else ROOT / "results" / default
    out.mkdir(parents=True, exist_ok=True)
    return out


def rotation(axis: int, degrees: float) -> np.ndarray:
    """(3, 3) rotation by ``degrees`` about coordinate axis ``axis`` (right-handed)."""
    a = np.radians(degrees)
    c, s = np.cos(a), np.sin(a)
    i, j = (axis + 1) % 3, (axis + 2) % 3
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def rotated_source(V: np.ndarray, axis: int, angle: float) -> np.ndarray:
    """``V`` rotated by ``angle`` degrees about coordinate axis ``axis`` through its box center."""
    c = (V.max(axis=0) + V.min(axis=0)) / 2
    return (V - c) @ rotation(axis, angle).T + c


def row_of(result, **extra) -> dict:
    """One table row: ``extra`` then the metric columns of a registration or baseline."""
    row = dict(extra)
    for key, _, _ in METRIC_COLUMNS:
        if key == "seconds":
            row[key] = float(sum(v for k, v in result.timings.items() if k != "sdf_queries"))
        else:
            row[key] = result.metrics.get(key, float("nan"))
    return row


def write_table(rows: list[dict], out: Path, stem: str, columns: list[tuple[str, str, str]]) -> str:
    """Write ``<stem>.csv`` (every key) and ``<stem>.md`` (``columns``: key, header, format);
    returns the markdown."""
    write_csv(out / f"{stem}.csv", rows)
    md = ["| " + " | ".join(h for _, h, _ in columns) + " |", "|" + "---|" * len(columns)]
    for r in rows:
        cells = []
        for key, _, fmt in columns:
            v = r.get(key, "")
            cells.append(fmt.format(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v))
        md.append("| " + " | ".join(cells) + " |")
    text = "\n".join(md) + "\n"
    (out / f"{stem}.md").write_text(text)
    return text


class MeshStore:
    """Registered vertices of every run in ``<out>/meshes.npz`` (rewritten after each run),
    so plots can be redrawn without registering again (``--plot-only``)."""

    def __init__(self, out: Path, reset: bool):
        self.path = out / "meshes.npz"
        self.arrays: dict[str, np.ndarray] = {}
        if not reset and self.path.is_file():
            self.arrays = dict(np.load(self.path))

    def __setitem__(self, key: str, V: np.ndarray) -> None:
        self.arrays[key] = np.asarray(V)
        np.savez_compressed(self.path, **self.arrays)

    def __getitem__(self, key: str) -> np.ndarray:
        return self.arrays[key]

    def __contains__(self, key: str) -> bool:
        return key in self.arrays


def save_meta(out: Path, **meta) -> None:
    (out / "meta.json").write_text(json.dumps(meta, indent=2, default=str) + "\n")


def load_rows(out: Path, stem: str) -> list[dict]:
    with open(out / f"{stem}.csv") as fh:
        rows = list(csv.DictReader(fh))
    for r in rows:
        for k, v in r.items():
            try:
                r[k] = float(v)
            except (TypeError, ValueError):
                pass
    return rows


def options_from(args) -> "mm.RegistrationOptions":
    changes = {"grid": args.grid, "modes": args.modes}
    if getattr(args, "max_iterations", None):
        changes["max_iterations"] = args.max_iterations
    changes.update(parse_overrides(args.set))
    return mm.RegistrationOptions().replace(**changes)


def add_common(ap, grid: int = 48, modes: int = 20) -> None:
    ap.add_argument("--grid", type=int, default=grid, help=f"quadrature grid (default {grid})")
    ap.add_argument("--modes", type=int, default=modes, help=f"m_max of ours (default {modes})")
    ap.add_argument("--max-iterations", type=int, default=None, help="cap on gradient steps of ours")
    ap.add_argument("--set", nargs="*", default=[], metavar="OPTION=VALUE",
                    help="override RegistrationOptions fields, e.g. --set preconditioner=none")
    ap.add_argument("--out", default=None, help="output folder (default results/<experiment>)")
    ap.add_argument("--plot-only", action="store_true", help="redraw plots from saved results")


def start(ap, name: str, pair: bool = True):
    """Parse the arguments (after :func:`add_common`); returns ``args, out, store`` and, with
    ``pair``, the paths of ``--source`` and ``--target``."""
    args = ap.parse_args()
    out = out_dir(name, args.out)
    store = MeshStore(out, reset=not args.plot_only)
    if not pair:
        return args, out, store
    return args, out, store, mesh_path(args.source), mesh_path(args.target)


def line_plot(path: Path, series: list[tuple], xlabel: str, ylabel: str, dpi: int = 90) -> None:
    """One small line plot: ``series`` of ``(xs, ys, style, label, plot_kwargs)``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.2))
    for xs, ys, style, label, kw in series:
        ax.plot(xs, ys, style, label=label, **kw)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
