"""Paths shared by the scripts."""

from __future__ import annotations

import csv
from pathlib import Path

from morphmodes_vol.datasets import shared_data_dir as data_dir  # noqa: F401
from morphmodes_vol.options import parse_setting

ROOT = Path(__file__).resolve().parents[1]

SETS = {
    "tuning": [("lion", range(1, 10)), ("cat", range(1, 10))],
    "validation": [("dance", range(1, 7)), ("jump", range(1, 6)), ("chicken", range(1, 7)), ("face", range(1, 6))],
}
"""The tuning and validation sets of ``../shared/data`` (its README): body, pose numbers."""


def plan(sets: list[str], quick: dict | None, only: list[str]) -> list[dict]:
    """The pairs of ``sets``: set, name (the target pose), source and target mesh names; with
    ``quick`` (set -> pose names) only those, with ``only`` only these names."""
    out = []
    for s in sets:
        for body, frames in SETS[s]:
            for i in frames:
                name = f"{body}-{i:02d}"
                if (quick and name not in quick[s]) or (only and name not in only):
                    continue
                out.append({"set": s, "pair": name, "source": f"{body}-reference", "target": name})
    return out


def mesh_file(name: str) -> Path:
    """The mesh of pose (or reference) ``name`` in ``../shared/data``."""
    return data_dir() / f"{name.rsplit('-', 1)[0]}-poses" / f"{name}.obj"


def parse_overrides(items: list[str]) -> dict:
    """``["grid=48", "warped_pass=false"]`` -> ``{"grid": 48, "warped_pass": False}``: the
    values read as the command line's ``--set`` reads them (TOML values, else a string)."""
    return dict(parse_setting(item) for item in items)


def write_csv(path, rows: list[dict]) -> None:
    """Rows (dicts) to a CSV file; the columns are the union of the rows' keys, in order."""
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
