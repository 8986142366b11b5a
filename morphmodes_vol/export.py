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
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from .errors import OptionError, OutputPathError

__all__ = ["write_outputs", "output_names", "check_output_path", "atomic_write_bytes", "atomic_path",
           "library_versions", "MESH_FORMATS"]

log = logging.getLogger(__name__)

MESH_FORMATS = ("ply", "obj", "off", "stl")


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = ".tmp") -> Iterator[Path]:
    """A temporary file name in the folder of ``path``; when the block ends without error
    the file there replaces ``path`` (with the usual permissions), else it is removed. For
    writers that need a file name (OpenVDB); :func:`atomic_write_bytes` is built on it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the usual permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def output_names(mesh_format: str = "ply") -> tuple[str, ...]:
    """The files :func:`write_outputs` writes in its folder."""
    return (f"registered.{mesh_format}", "state.npz", "correspondence.npz", "report.json")


def _nearest_existing(path: Path) -> Path:
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def check_output_path(path: str | os.PathLike, kind: str = "folder", writes=(), inputs=()) -> Path:
    """Check, before any work, that ``path`` can take the outputs; nothing is created.

    Parameters
    ----------
    path : path
        The output folder (``kind="folder"``) or file (``kind="file"``).
    kind : {"folder", "file"}
    writes : iterable of path
        The files that will be written (for a folder, relative to it; default: ``path``
        itself for a file).
    inputs : iterable of path
        Input files, none of which may be among ``writes``.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    OutputPathError
        If ``path`` is a file where a folder is expected or a folder where a file is, if its
        folder cannot be created (a file on the way) or written (a trial file cannot be made
        in it or in its nearest existing parent), or if an output would overwrite an input.

    Examples
    --------
    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     _ = check_output_path(Path(d) / "new" / "folder")       # fine: it will be created
    ...     (Path(d) / "a.obj").write_text("")
    ...     check_output_path(Path(d) / "a.obj")
    Traceback (most recent call last):
    ...
    morphmodes_vol.errors.OutputPathError: output folder ...a.obj is an existing file
    """
    if kind not in ("folder", "file"):
        raise ValueError(f"kind must be 'folder' or 'file', got {kind!r}")
    path = Path(path)
    if kind == "folder" and path.exists() and not path.is_dir():
        raise OutputPathError(f"output folder {path} is an existing file")
    if kind == "file" and path.is_dir():
        raise OutputPathError(f"output file {path} is an existing folder; give a file name")
    folder = path if kind == "folder" else path.parent
    existing = _nearest_existing(folder.absolute())
    if not existing.is_dir():
        raise OutputPathError(f"output folder {folder} cannot be created: {existing} is a file")
    try:  # the only reliable test (os.access is wrong for root and read-only file systems)
        fd, trial = tempfile.mkstemp(prefix=".morphmodes-write-test.", dir=existing)
        os.close(fd)
        os.unlink(trial)
    except OSError as exc:
        verb = "written" if existing == folder.absolute() else "created"
        raise OutputPathError(f"output folder {folder} cannot be {verb}: {exc.strerror} "
                              f"({existing})") from None
    targets = [folder / w for w in writes] if kind == "folder" else [Path(w) for w in (writes or [path])]
    outputs = {os.path.realpath(t): t for t in targets}
    for item in inputs:
        if item is not None and os.path.realpath(item) in outputs:
            raise OutputPathError(f"output {outputs[os.path.realpath(item)]} would overwrite the input {item}")
    return path


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and a rename,
    so the file is either absent, the old one, or complete."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())


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
      and ``barycentrics`` (n, 3) of the closest point on it (not written when the target was
      given as an SDF grid, which has no faces).

    ``report.json`` is written last, so its presence marks a complete output folder.

    Returns
    -------
    dict of str to Path
    """
    outdir = check_output_path(outdir, "folder")
    outdir.mkdir(parents=True, exist_ok=True)
    # an old report next to new files would mark a half-rewritten folder as complete
    (outdir / "report.json").unlink(missing_ok=True)
    paths = dict(zip(("mesh", "state", "correspondence", "report"),
                     (outdir / name for name in output_names(mesh_format))))
    if result.correspondence_faces is None:  # a target given as an SDF grid has no faces
        paths.pop("correspondence").unlink(missing_ok=True)  # none left from an older run
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
    if "correspondence" in paths:
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
