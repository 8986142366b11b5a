"""The on-disk cache of stage products, keyed by mesh content and parameters.

A key is the SHA-256 of the product kind, a format version, the loaded vertex and face
arrays (bytes, dtype and shape, so an edited mesh never reuses a stale product whatever its
file name) and the parameters the product depends on. Products are ``.npz`` files written
atomically; a per-key lock file (``fcntl.flock``, released by the kernel when a process dies,
even by ``kill -9``) makes concurrent workers build a shared product once.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import logging
import os
from pathlib import Path
from typing import Callable, TypeVar

import numpy as np

from ..export import atomic_write_bytes

__all__ = ["mesh_digest", "product_key", "ProductCache"]

log = logging.getLogger(__name__)

# bump when a product's definition changes, so old cache entries are never reused
_VERSION = 1

T = TypeVar("T")


def mesh_digest(V: np.ndarray, F: np.ndarray) -> str:
    """SHA-256 of a loaded mesh: shapes, dtypes and bytes of ``V (n, 3)`` and ``F (m, 3)``.

    Examples
    --------
    >>> V = np.zeros((3, 3)); F = np.array([[0, 1, 2]])
    >>> mesh_digest(V, F) == mesh_digest(V.copy(), F.astype(np.int64))
    True
    >>> mesh_digest(V + 1e-12, F) == mesh_digest(V, F)
    False
    """
    h = hashlib.sha256()
    for a in (np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int64)):
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def product_key(kind: str, digests: list[str], params: dict) -> str:
    """Key of a product: kind, version, the meshes it depends on and its parameters."""
    blob = json.dumps({"kind": kind, "version": _VERSION, "meshes": digests, "params": params},
                      sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


@contextlib.contextmanager
def _locked(path: Path):
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock, a shared product may be built twice
        yield
        return
    with open(path, "a+") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


class ProductCache:
    """Stage products in a folder every worker can read and write.

    Parameters
    ----------
    folder : path
        Created when missing.
    """

    def __init__(self, folder: str | os.PathLike):
        self.folder = Path(folder)

    def path(self, kind: str, key: str) -> Path:
        return self.folder / kind / f"{key}.npz"

    def get_or_build(self, kind: str, key: str, build: Callable[[], T],
                     to_arrays: Callable[[T], dict], from_arrays: Callable[[dict], T]) -> tuple[T, bool]:
        """The product ``kind``/``key``: loaded when cached, else built, stored and returned.

        Returns
        -------
        product
        hit : bool
            ``True`` when it came from the cache.
        """
        path = self.path(kind, key)
        path.parent.mkdir(parents=True, exist_ok=True)
        with _locked(path.with_suffix(".lock")):
            if path.is_file():
                try:
                    with np.load(path) as data:
                        return from_arrays({k: data[k] for k in data.files}), True
                except (OSError, ValueError, KeyError) as exc:  # unreadable: rebuild it
                    log.warning("cache entry %s unreadable (%s); rebuilding it", path, exc)
            product = build()
            buf = io.BytesIO()
            np.savez(buf, **to_arrays(product))
            atomic_write_bytes(path, buf.getvalue())
            return product, False
