"""Where the shared real meshes are (lion and cat poses), for tests, studies and benchmarks."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["shared_data_dir"]

_REPO = Path(__file__).resolve().parents[1]


def shared_data_dir() -> Path | None:
    """``$MORPHMODES_DATA`` if set, else ``../shared/data`` beside the repository; ``None``
    when that folder does not exist (callers skip)."""
    env = os.environ.get("MORPHMODES_DATA")
    path = Path(env) if env else _REPO.parent / "shared" / "data"
    return path if path.is_dir() else None
