"""Paths shared by the scripts."""

from __future__ import annotations

from pathlib import Path

from morphmodes_vol.datasets import shared_data_dir as data_dir  # noqa: F401

ROOT = Path(__file__).resolve().parents[1]
