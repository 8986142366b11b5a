"""Stage 4, export: atomic writers of the registered mesh, the report, the state and the
dense correspondence."""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import platform
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from .errors import OptionError

__all__ = ["write_outputs", "atomic_write_bytes", "library_versions", "MESH_FORMATS"]

log = logging.getLogger(__name__)

MESH_FORMATS = ("ply", "obj", "off", "stl")


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and a rename,
    so the file is either absent, the old one, or complete."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the usual permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _npz_bytes(**arrays: Any) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def mesh_bytes(V: np.ndarray, F: np.ndarray, fmt: str) -> bytes:
    """Serialize ``(V, F)`` as ``fmt`` (one of :data:`MESH_FORMATS`) with trimesh, keeping
    vertex order."""
    import trimesh

    if fmt not in MESH_FORMATS:
        raise OptionError(f"mesh format {fmt!r}: expected one of {MESH_FORMATS}")
    mesh = trimesh.Trimesh(vertices=V, faces=F, process=False)
    data = mesh.export(file_type=fmt)
    return data.encode() if isinstance(data, str) else bytes(data)


def library_versions() -> dict[str, str]:
    """Versions of Python and the libraries a result depends on."""
    from importlib import metadata

    versions = {"python": platform.python_version()}
    for dist in ("morphmodes-vol", "numpy", "scipy", "trimesh", "open3d", "libigl"):
        try:
            versions[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            versions[dist] = "not installed"
    return versions


def _digest(*arrays: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def _finite_or_null(obj: Any) -> Any:
    """``obj`` with every NaN or infinite float replaced by ``None``, recursively."""
    if isinstance(obj, float):
        return obj if np.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite_or_null(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite_or_null(v) for v in obj]
    return obj


def write_outputs(result, outdir: str | os.PathLike, inputs: dict | None = None,
                  mesh_format: str = "ply") -> dict[str, Path]:
    """Write a :class:`~morphmodes_vol.RegistrationResult` to ``outdir``.

    Files (each written atomically):

    - ``registered.<fmt>``: the registered source, original frame, source vertex order;
    - ``report.json``: inputs, options, status, energies, timings, metrics, versions;
    - ``state.npz``: ``W`` (n, m_max), ``eigenvalues``, ``T`` (m, 3, 4), ``z`` (12m,),
      the normalization and the history arrays;
    - ``correspondence.npz``: ``faces`` (n,) closest target face of every registered vertex
      and ``barycentrics`` (n, 3) of the closest point on it.

    ``report.json`` is written last, so its presence marks a complete output folder.

    Returns
    -------
    dict of str to Path
    """
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    # an old report next to new files would mark a half-rewritten folder as complete
    (outdir / "report.json").unlink(missing_ok=True)
    paths = {
        "mesh": outdir / f"registered.{mesh_format}",
        "state": outdir / "state.npz",
        "correspondence": outdir / "correspondence.npz",
        "report": outdir / "report.json",
    }
    atomic_write_bytes(paths["mesh"], mesh_bytes(result.vertices, result.faces, mesh_format))
    h = result.history
    atomic_write_bytes(
        paths["state"],
        _npz_bytes(
            W=result.weights,
            eigenvalues=result.eigenvalues,
            T=result.T,
            z=result.z,
            normalization_center=result.normalization.center,
            normalization_scale=np.float64(result.normalization.scale),
            energy=np.asarray(h.energy),
            step_rms=np.asarray(h.step_rms),
            modes=np.asarray(h.modes, dtype=np.int64),
            stage_starts=np.asarray(h.stage_starts, dtype=np.int64),
            stage_ends=np.asarray(h.stage_ends, dtype=str),
            stage_seconds=np.asarray(h.stage_seconds),
            evaluations=np.int64(h.evaluations),
        ),
    )
    atomic_write_bytes(
        paths["correspondence"],
        _npz_bytes(faces=result.correspondence_faces, barycentrics=result.correspondence_barycentrics),
    )
    report = {
        "inputs": dict(inputs or {}),
        "source": {
            "vertices": int(result.vertices.shape[0]),
            "faces": int(result.faces.shape[0]),
        },
        "target": {
            "vertices": int(result.target_vertices.shape[0]) if result.target_vertices is not None else None,
            "faces": int(result.target_faces.shape[0]) if result.target_faces is not None else None,
        },
        "options": result.options.to_dict(),
        "status": result.status,
        "modes": result.modes,
        "evaluations": result.evaluations,
        "timings": {k: float(v) for k, v in result.timings.items()},
        "metrics": result.metrics,
        "history": h.to_dict(),
        "registered_sha256_16": _digest(result.vertices),
        "versions": library_versions(),
        "command": sys.argv if inputs and inputs.get("cli") else None,
    }
    # strict JSON: a NaN or infinite figure (a rolled-back run) is written as null
    text = json.dumps(_finite_or_null(report), indent=2, allow_nan=False)
    atomic_write_bytes(paths["report"], (text + "\n").encode())
    log.info("wrote %s", ", ".join(str(p) for p in paths.values()))
    return paths
