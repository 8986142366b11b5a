"""BLAS on one thread, shared by every thread of the process (:func:`single_threaded_blas`).

A registration runs its BLAS on one thread, for two reasons:

- speed: its dense products are small (at most n x 4m and 12m x 12m), and a multithreaded
  BLAS only adds wake-up costs to them;
- reproducibility: the dense eigenproblem of a small mesh's skinning eigenmodes gives, in the
  space of a repeated eigenvalue, eigenvectors that depend on the last bits of BLAS's sums,
  so on a symmetric mesh the basis, and the registration's path, changed with BLAS's thread
  count. On one thread they do not. (On the 80k-vertex lion the eigenmodes take 2.8 s on one
  thread against 2.7 s on two.)
"""

from __future__ import annotations

import threading
from contextlib import contextmanager

from threadpoolctl import OpenBLASController, threadpool_limits

__all__ = ["single_threaded_blas"]

_blas_lock = threading.Lock()
_blas_users = 0
_blas_limiter = None


def release_blas_control() -> None:
    """threadpoolctl >= 3.8 lets one thread at a time set OpenBLAS's process-wide pool (the
    others' calls do nothing): give that control back if this thread holds it, so that
    whichever thread leaves last can restore the limit."""
    release = getattr(OpenBLASController, "clear_controlling_thread", None)
    if release is not None:
        release()


@contextmanager
def single_threaded_blas():
    """Context in which BLAS runs on one thread.

    The products of Algorithm 1 are small (at most n x 4m and 12m x 12m): a multithreaded
    BLAS only adds wake-up costs, which are pathological on a busy machine.

    BLAS's thread count belongs to the process, not to the calling thread. So the contexts
    of all threads count as one: the first to enter limits it, the last to leave restores
    what the first found, whichever threads those are. With ``threadpool_limits`` alone,
    registrations run from two threads at once that overlap (A enters, B enters, A leaves,
    B leaves) let B run its remaining steps with every BLAS thread, and then restore the
    limit of 1 that B found, leaving BLAS on one thread for the rest of the process.
    A limit that another thread holds (threadpoolctl >= 3.8) is left alone.
    """
    global _blas_users, _blas_limiter
    with _blas_lock:
        if _blas_users == 0:
            _blas_limiter = threadpool_limits(limits=1, user_api="blas")
            release_blas_control()
        _blas_users += 1
    try:
        yield
    finally:
        with _blas_lock:
            _blas_users -= 1
            if _blas_users == 0:
                _blas_limiter.restore_original_limits()
                release_blas_control()
                _blas_limiter = None
