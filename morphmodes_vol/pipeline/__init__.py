"""Pipelines over datasets: a TOML definition of many pairs, run as independent tasks with
cached stage products, resumable, on a local process pool or a Dask cluster.

Quick use::

    from morphmodes_vol.pipeline import load_pipeline, run_pipeline
    run = run_pipeline(load_pipeline("pipelines/lion_poses.toml"), workers=2)
    run.failed, run.paths["md"]

Format reference, caching and resume: docs/pipelines.md.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from .definition import PairSpec, Pipeline, load_pipeline, parse_pipeline
from .executor import EXECUTORS, Executor, execute
from .summary import markdown_table, write_summary
from .task import run_pair

__all__ = ["Pipeline", "PairSpec", "PipelineRun", "load_pipeline", "parse_pipeline", "run_pipeline",
           "run_pair", "execute", "EXECUTORS", "markdown_table"]

log = logging.getLogger(__name__)


@dataclass
class PipelineRun:
    """What a run did.

    Attributes
    ----------
    rows : list of dict
        One summary row per pair (columns of ``summary.csv``).
    results : list of dict
        The pair tasks' results (``state`` ``ok``, ``skipped`` or ``failed``).
    paths : dict of str to Path
        ``csv``, ``json``, ``md`` and (with matplotlib) ``png``.
    seconds : float
    """

    rows: list[dict]
    results: list[dict]
    paths: dict[str, Path] = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def failed(self) -> int:
        return sum(r["state"] == "failed" for r in self.rows)


def run_pipeline(pipeline: Pipeline, executor: Executor = "local", workers: int | None = None,
                 scheduler: str | None = None, client=None,
                 on_event: Callable[[str, str], None] | None = None,
                 on_result: Callable[[dict], None] | None = None) -> PipelineRun:
    """Run every pair of ``pipeline`` (skipping complete ones) and write the summary.

    Parameters are those of :func:`~morphmodes_vol.pipeline.executor.execute`.
    """
    pipeline.output.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    results = execute(pipeline.pairs, executor, workers, scheduler, client, on_event, on_result)
    seconds = time.perf_counter() - t
    info = {"executor": executor, "workers": workers, "scheduler": scheduler, "seconds": seconds,
            "counts": {s: sum(r["state"] == s for r in results) for s in ("ok", "skipped", "failed")},
            "cache": str(pipeline.cache_dir), "cpu_count": os.cpu_count()}
    rows, paths = write_summary(pipeline, results, info)
    log.info("pipeline %s: %s in %.1fs", pipeline.name, info["counts"], seconds)
    return PipelineRun(rows=rows, results=results, paths=paths, seconds=seconds)
