"""Run a serial numba kernel on slices of its outer loop, one slice per thread.

numba compiles a ``parallel=True`` kernel much more slowly than the same loops serial (the
parfor passes, then a gufunc for each parallel loop), a cost paid on a first run before the
user sees anything. A kernel whose outer loop has independent iterations is therefore
compiled serial with ``nogil=True``, takes the half-open range ``lo, hi`` of that loop as its
last two arguments, and :func:`run_slices` runs it on consecutive slices of the range in a
pool of Python threads: each iteration does what it did under ``prange`` (whose default
scheduling also gives each thread one consecutive block), so the results are the same bit for
bit, at the parallel speed. There is one slice per numba thread of the calling thread
(:func:`numba.get_num_threads`; ``NUMBA_NUM_THREADS`` and :func:`numba.set_num_threads` apply).
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor, wait

import numba

_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def thread_count() -> int:
    """Threads the kernels of the calling thread may use (numba's setting)."""
    return max(1, int(numba.get_num_threads()))


def slices(n: int, parts: int) -> list[tuple[int, int]]:
    """Split ``range(n)`` into at most ``parts`` consecutive, non-empty ``(lo, hi)`` slices."""
    if n <= 0:
        return []
    parts = max(1, min(int(parts), int(n)))
    return [(n * i // parts, n * (i + 1) // parts) for i in range(parts)]


def _pool() -> ThreadPoolExecutor:
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(max_workers=max(1, numba.config.NUMBA_NUM_THREADS - 1),
                                       thread_name_prefix="plenopiv-kernel")
        return _POOL


def run_slices(kernel, n: int, *args, parts: int | None = None) -> None:
    """Call ``kernel(*args, lo, hi)`` for the slices of ``range(n)``, in parallel.

    ``kernel`` must be compiled with ``nogil=True`` and write disjoint parts of its outputs
    for disjoint slices. The calling thread runs the first slice; an exception of any slice
    is raised here after all have ended. An interrupt of the calling thread (Ctrl-C, or
    SIGTERM through :func:`plenopiv.cli.sigterm_as_interrupt`) is raised at once, the other slices
    not waited for: the interrupted slice may hold a lock they wait on (numba's compiler
    takes llvmlite's when a kernel is first loaded, and an interrupt inside it never
    releases it), and waiting would never end.
    """
    parts_ = thread_count() if parts is None else parts
    work = slices(n, parts_)
    if len(work) <= 1:
        for lo, hi in work:
            kernel(*args, lo, hi)
        return
    futures = [_pool().submit(kernel, *args, lo, hi) for lo, hi in work[1:]]
    try:
        kernel(*args, *work[0])
    except Exception:
        wait(futures)
        raise
    except BaseException:
        for future in futures:
            future.cancel()
        raise
    errors = [f.exception() for f in futures]
    for error in errors:
        if error is not None:
            raise error
