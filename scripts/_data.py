"""Paths shared by the scripts."""

from __future__ import annotations

import ast
import csv
from pathlib import Path

from morphmodes_vol.datasets import shared_data_dir as data_dir  # noqa: F401

ROOT = Path(__file__).resolve().parents[1]


def parse_overrides(items: list[str]) -> dict:
    """``["grid=48", "preconditioner=none"]`` -> ``{"grid": 48, "preconditioner": "none"}``."""
    out = {}
    for item in items:
        key, _, value = item.partition("=")
        try:
            out[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            out[key] = value
    return out


def write_csv(path, rows: list[dict]) -> None:
    """Rows (dicts) to a CSV file; the columns are the union of the rows' keys, in order."""
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
