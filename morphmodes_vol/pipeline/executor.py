"""Executors: run independent pair tasks in this process, a local process pool, or on a Dask
cluster. Every executor runs the same :func:`~morphmodes_vol.pipeline.task.run_pair`, so the
numbers do not depend on which one ran them."""

from __future__ import annotations

import logging
import os
import queue
import threading
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Callable, Literal

from ..errors import OptionError
from .definition import PairSpec
from .task import run_pair

__all__ = ["Executor", "EXECUTORS", "execute"]

log = logging.getLogger(__name__)

Executor = Literal["local", "dask"]
EXECUTORS = ("local", "dask")
_TOPIC = "morphmodes-vol-pipeline"

Events = Callable[[str, str], None]


class _QueueEvents:
    """Picklable event sink of a pool worker: puts ``(pair, text)`` on a managed queue."""

    def __init__(self, q):
        self.q = q

    def __call__(self, name: str, text: str) -> None:
        self.q.put((name, text))


class _DaskEvents:
    """Event sink of a Dask task: a worker event the client subscribed to."""

    def __call__(self, name: str, text: str) -> None:
        from distributed import get_worker

        get_worker().log_event(_TOPIC, {"pair": name, "text": text})


def _failed(spec: PairSpec, exc: BaseException) -> dict:
    return {"name": spec.name, "state": "failed", "key": None, "seconds": 0.0,
            "error": f"worker lost: {type(exc).__name__}: {exc}"}


def _serial(specs, on_event: Events, on_result) -> None:
    for spec in specs:
        on_result(run_pair(spec, on_event))


def _pool(specs, workers: int, on_event: Events, on_result) -> None:
    import multiprocessing as mp

    ctx = mp.get_context("spawn")  # no fork of a process holding Open3D/BLAS threads
    with ctx.Manager() as manager:
        q = manager.Queue()
        stop = threading.Event()

        def drain() -> None:
            while not stop.is_set():
                try:
                    on_event(*q.get(timeout=0.2))
                except queue.Empty:
                    continue
                except (EOFError, OSError):
                    return

        thread = threading.Thread(target=drain, daemon=True)
        thread.start()
        try:
            with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
                futures = {pool.submit(run_pair, spec, _QueueEvents(q)): spec for spec in specs}
                for fut in as_completed(futures):
                    try:
                        on_result(fut.result())
                    except Exception as exc:  # a worker process died (segfault, OOM kill)
                        on_result(_failed(futures[fut], exc))
        finally:
            stop.set()
            thread.join()


def _dask(specs, workers: int | None, scheduler: str | None, client, on_event: Events, on_result) -> None:
    try:
        from distributed import Client, LocalCluster, as_completed as dask_completed
    except ImportError:
        raise OptionError(
            "the dask executor needs Dask: pip install 'dask[distributed]' "
            "(or the package's extra: pip install 'morphmodes-vol[dask]')"
        ) from None
    owned = []
    if client is None:
        if scheduler:
            client = Client(scheduler)
        else:
            cluster = LocalCluster(n_workers=workers or os.cpu_count() or 1, threads_per_worker=1,
                                   dashboard_address=":0", silence_logs=logging.WARNING)
            owned.append(cluster)
            client = Client(cluster)
        owned.insert(0, client)
    try:
        client.subscribe_topic(_TOPIC, lambda event: on_event(event[1]["pair"], event[1]["text"]))
        futures = {client.submit(run_pair, spec, _DaskEvents(), key=f"pair-{i}-{spec.name}", pure=False): spec
                   for i, spec in enumerate(specs)}
        for fut in dask_completed(futures):
            try:
                on_result(fut.result())
            except Exception as exc:  # the task's worker died
                on_result(_failed(futures[fut], exc))
        client.unsubscribe_topic(_TOPIC)
    finally:
        for thing in owned:
            thing.close()


def execute(specs: list[PairSpec], executor: Executor = "local", workers: int | None = None,
            scheduler: str | None = None, client=None, on_event: Events | None = None,
            on_result: Callable[[dict], None] | None = None) -> list[dict]:
    """Run every pair; return their result dictionaries in the order of ``specs``.

    Parameters
    ----------
    specs : list of PairSpec
    executor : {"local", "dask"}
        ``"local"``: a process pool of ``workers`` processes (default: the machine's CPU
        count, at most one per pair; ``1`` runs the pairs in this process). ``"dask"``: the
        Dask cluster at ``scheduler`` (a ``LocalCluster`` of ``workers`` processes when
        ``None``), or an existing ``distributed.Client`` passed as ``client``.
    on_event : callable ``(pair name, text)``, optional
        Progress at every state change of a pair.
    on_result : callable ``(dict)``, optional
        Called as each pair finishes.
    """
    if executor not in EXECUTORS:
        raise OptionError(f"executor {executor!r}: expected one of {EXECUTORS}")
    if workers is not None and workers < 1:
        raise OptionError(f"workers={workers}: expected a positive integer")
    results: dict[str, dict] = {}

    def collect(result: dict) -> None:
        results[result["name"]] = result
        if on_result is not None:
            on_result(result)

    events = on_event or (lambda name, text: None)
    if not specs:
        return []
    if executor == "dask":
        _dask(specs, workers, scheduler, client, events, collect)
    else:
        n = min(workers or os.cpu_count() or 1, len(specs))
        if n == 1:
            _serial(specs, events, collect)
        else:
            _pool(specs, n, events, collect)
    return [results[s.name] for s in specs]
