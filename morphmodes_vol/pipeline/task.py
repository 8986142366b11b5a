"""One pair of a pipeline, as an independent task: load, reuse or build the cached stage
products, optimize, export; or recognize that the pair's outputs are already complete.

A pair's folder is complete when its ``report.json`` (written last, atomically) records the
pair key of the current definition and the other files it lists exist. The pair key hashes
the loaded meshes (source, target, ground truth) and landmarks, the options, the output
format and the library version. A failure is written to ``failed.json`` and returned, never raised.
"""

from __future__ import annotations

import json
import logging
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import PipelineError
from ..export import atomic_write_bytes, write_outputs
from ..landmarks import load_landmarks
from ..mesh import load_mesh
from ..pointcloud import is_point_cloud_file
from ..register import Registration, scan_target
from ..stages import SourceEigenbasis, TargetField, source_eigenbasis, target_field
from .cache import ProductCache, mesh_digest, product_key
from .definition import PairSpec

__all__ = ["run_pair", "pair_key", "is_complete", "PAIR_FILES"]

log = logging.getLogger(__name__)

# files of a complete pair folder besides registered.<fmt>
PAIR_FILES = ("state.npz", "correspondence.npz", "report.json")


def pair_key(spec: PairSpec, digests: dict[str, str | None]) -> str:
    """Key of a pair's outputs: mesh contents, options, output format, library version."""
    from .. import __version__

    meshes = [digests["source"], digests["target"], digests.get("ground_truth") or ""]
    if digests.get("landmarks"):  # only then, so keys of pairs without landmarks stay as they were
        meshes.append(digests["landmarks"])
    return product_key("pair", meshes,
                       {"options": spec.options.to_dict(), "format": spec.resolved_format,
                        "library": __version__})


def is_complete(spec: PairSpec, key: str) -> bool:
    """Whether ``spec.outdir`` holds the complete outputs of the pair with ``key``."""
    try:
        report = json.loads((spec.outdir / "report.json").read_text())
    except (OSError, ValueError):
        return False
    if report.get("inputs", {}).get("pipeline", {}).get("key") != key:
        return False
    names = (f"registered.{spec.resolved_format}",) + PAIR_FILES
    return all((spec.outdir / n).is_file() for n in names)


def _emit(events: Any, name: str, text: str) -> None:
    if events is not None:
        try:
            events(name, text)
        except Exception:  # a progress display never fails a pair
            log.debug("progress event lost", exc_info=True)


def _product_line(what: str, info: dict) -> str:
    return f"{what} {'from the cache' if info['cached'] else 'built'} ({info['seconds']:.2f}s)"


def run_pair(spec: PairSpec, events: Any = None) -> dict:
    """Register one pair, or skip it when its outputs are complete.

    Parameters
    ----------
    spec : PairSpec
    events : callable ``(pair name, text)``, optional
        Receives a short line at every state change (stage, new mode).

    Returns
    -------
    dict
        ``name``, ``state`` (``"ok"``, ``"skipped"`` or ``"failed"``), ``key`` (``None`` when
        the meshes could not be read), ``error`` (failed pairs) and ``seconds``.
    """
    t0 = time.perf_counter()
    key = None
    try:
        _emit(events, spec.name, "load")
        inputs = _load_inputs(spec)
        key = pair_key(spec, inputs["digests"])
        if is_complete(spec, key):
            _emit(events, spec.name, "skipped (outputs complete)")
            return {"name": spec.name, "state": "skipped", "key": key, "seconds": 0.0}
        spec.outdir.mkdir(parents=True, exist_ok=True)
        (spec.outdir / "report.json").unlink(missing_ok=True)  # stale outputs of another key
        for tmp in spec.outdir.glob(".*.tmp"):  # a write cut short by a killed run
            tmp.unlink(missing_ok=True)
        basis, field, products = _products(spec, inputs, events)
        result = _register(spec, inputs, basis, field, events)
        _emit(events, spec.name, "export")
        seconds = time.perf_counter() - t0
        meta = {
            "source": str(spec.source), "target": str(spec.target),
            "ground_truth": None if spec.ground_truth is None else str(spec.ground_truth),
            "landmarks": None if spec.landmarks is None else str(spec.landmarks),
            "pipeline": {"pair": spec.name, "key": key, "variant": spec.variant,
                         "mesh_sha256": inputs["digests"], "products": products, "seconds": seconds},
        }
        write_outputs(result, spec.outdir, inputs=meta, mesh_format=spec.resolved_format)
        (spec.outdir / "failed.json").unlink(missing_ok=True)
        _emit(events, spec.name, f"done: {result.status}, {seconds:.1f}s")
        return {"name": spec.name, "state": "ok", "key": key, "seconds": seconds}
    except Exception as exc:  # one pair's failure never stops the run
        seconds = time.perf_counter() - t0
        error = f"{type(exc).__name__}: {exc}"
        log.debug("pair %s failed", spec.name, exc_info=True)
        record = {"pair": spec.name, "key": key, "error": error, "seconds": seconds,
                  "traceback": traceback.format_exc(limit=8)}
        try:
            atomic_write_bytes(Path(spec.outdir) / "failed.json", (json.dumps(record, indent=2) + "\n").encode())
        except OSError:
            log.warning("cannot write %s/failed.json", spec.outdir)
        _emit(events, spec.name, f"FAILED: {error}")
        return {"name": spec.name, "state": "failed", "key": key, "error": error, "seconds": seconds}


def _load_inputs(spec: PairSpec) -> dict:
    """The pair's meshes (a scan target as its Poisson surface), ground truth and landmarks,
    and the content digests that key its outputs and cached products."""
    Vs, Fs = load_mesh(spec.source, min_vertices=4)
    if is_point_cloud_file(spec.target):  # a scan: its Poisson surface (or its SDF) is the target
        scanned = scan_target(spec.target, spec.options)
        if not isinstance(scanned, tuple):
            raise PipelineError(f"{spec.target}: a point-cloud target in a pipeline needs "
                                "point_sdf = 'poisson' (its surface is cached as a mesh's)")
        Vt, Ft = scanned
    else:
        Vt, Ft = load_mesh(spec.target)
    digests = {"source": mesh_digest(Vs, Fs), "target": mesh_digest(Vt, Ft)}
    truth = None
    if spec.ground_truth is not None:
        if spec.ground_truth == spec.target and is_point_cloud_file(spec.target):
            raise PipelineError(f"{spec.target}: a scan has no vertex order to be the ground truth; "
                                "give the intact mesh as ground_truth")
        truth = Vt if spec.ground_truth == spec.target else load_mesh(spec.ground_truth)[0]
        digests["ground_truth"] = mesh_digest(truth, np.zeros((0, 3)))
    landmarks = None
    if spec.landmarks is not None:
        landmarks = load_landmarks(spec.landmarks, len(Vs))
        digests["landmarks"] = mesh_digest(landmarks.points, landmarks.indices[:, None])
    return {"source": (Vs, Fs), "target": (Vt, Ft), "truth": truth, "landmarks": landmarks, "digests": digests}


def _products(spec: PairSpec, inputs: dict, events) -> tuple:
    """The source's eigenbasis and the target's dense SDF, from the cache or built (and
    cached); with what each cost."""
    opts, digests = spec.options, inputs["digests"]
    (Vs, Fs), (Vt, Ft) = inputs["source"], inputs["target"]
    cache = ProductCache(spec.cache_dir)
    products = {}
    t = time.perf_counter()
    basis, hit = cache.get_or_build(
        "eigenbasis", product_key("eigenbasis", [digests["source"]], {"modes": opts.modes, "seed": opts.seed}),
        lambda: source_eigenbasis(Vs, Fs, opts.modes, opts.seed),
        SourceEigenbasis.to_arrays, SourceEigenbasis.from_arrays,
    )
    products["eigenbasis"] = {"cached": hit, "seconds": time.perf_counter() - t}
    t = time.perf_counter()
    _emit(events, spec.name, _product_line("eigenbasis", products["eigenbasis"]))
    if opts.target_backend == "dense":
        field, hit = cache.get_or_build(
            "target_sdf",
            product_key("target_sdf", [digests["target"]],
                        {"resolution": opts.resolved_target_grid, "padding": opts.padding,
                         "sign": opts.target_sign}),
            lambda: target_field(Vt, Ft, opts.resolved_target_grid, opts.padding, opts.target_sign),
            TargetField.to_arrays, TargetField.from_arrays,
        )
    else:  # only dense fields are cached: Registration builds the vdb level set per pair
        field, hit = None, False
    products["target_sdf"] = {"cached": hit, "seconds": time.perf_counter() - t}
    _emit(events, spec.name, _product_line("target SDF", products["target_sdf"]))
    return basis, field, products


def _register(spec: PairSpec, inputs: dict, basis, field, events):
    """The registration of the pair, its progress as a line per new mode."""
    reg = Registration(inputs["source"], inputs["target"], spec.options, eigenbasis=basis, target_sdf=field,
                       landmarks=inputs["landmarks"])
    modes = [0]

    def progress(e) -> None:
        if e.modes != modes[0]:
            modes[0] = e.modes
            _emit(events, spec.name, f"optimize modes {e.modes}/{e.max_modes}")

    result = reg.run(progress=progress, ground_truth=inputs["truth"])
    if not np.all(np.isfinite(result.vertices)):
        raise FloatingPointError("the optimization diverged: non-finite registered vertices")
    return result
