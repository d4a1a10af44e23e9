"""Up-front size checks: refuse work that cannot fit this machine before allocating anything.

A volume, a sensor or an array beyond the memory available is refused at once with the
figure (:class:`~plenopiv.errors.ResourceError`), never after minutes of estimation or with
numpy's ``_ArrayMemoryError`` traceback.
"""

from __future__ import annotations

import ctypes
import functools
import os
import platform

from plenopiv.errors import ResourceError

#: Bytes per voxel of a reconstruction besides its weights: the float32 volume, the MART
#: correction and first guess, the line-of-sight mask and the particle search (~8 float32).
BYTES_PER_VOXEL = 32
#: Bytes per sensor pixel of rendering or reading an image (float64 irradiance, its copies).
BYTES_PER_PIXEL = 40


def prefer_small_pages() -> bool:
    """Stop NumPy asking the kernel for transparent huge pages for this process's arrays.

    NumPy marks every large array ``madvise(MADV_HUGEPAGE)`` on Linux. Where memory is
    fragmented (a long-running or virtual machine), each first touch of such an array can
    stall in the kernel's compaction, for longer than the computation that fills it
    (``benchmarks/full_camera.py``, docs/validation/real_arrays.md). The arrays here are
    written once per stage, where huge pages save little. Called by the ``plenopiv`` command
    and each batch worker, not on import (a library does not change its caller's process);
    an explicit ``NUMPY_MADVISE_HUGEPAGE`` in the environment is left as the user set it.

    Returns
    -------
    bool
        True when NumPy's setting was changed by this call.
    """
    if "NUMPY_MADVISE_HUGEPAGE" in os.environ:
        return False
    try:
        from numpy._core.multiarray import _set_madvise_hugepage
    except ImportError:                                 # pragma: no cover - other NumPy
        return False
    return bool(_set_madvise_hugepage(False))


#: glibc ``mallopt`` parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4
#: Free memory at the top of the heap kept for reuse rather than handed back, bytes.
KEEP_FREED_BYTES = 256 << 20


#: The glibc allocator's environment variables: where the user set one, the allocator is
#: left as they chose.
ALLOCATOR_ENV_VARS = ("MALLOC_MMAP_MAX_", "MALLOC_TRIM_THRESHOLD_")


def allocator_environment(environ=None) -> tuple[tuple[str, str], ...]:
    """The allocator variables set in ``environ`` (default: this process's), as pairs.

    What a command hands its batch workers (:func:`own_process_memory`), whose own
    environment is their launcher's as much as the user's.
    """
    environ = os.environ if environ is None else environ
    return tuple((k, environ[k]) for k in ALLOCATOR_ENV_VARS if k in environ)


def reuse_freed_memory(user_environment=None) -> bool:
    """Let this process reuse the memory it frees instead of handing it back at once.

    glibc serves every allocation above 32 MB (an image's rays, a volume's slabs) by a fresh
    ``mmap`` and returns it on ``free``, so the next array of that size faults in again page
    by page: about 5 million faults and a quarter of the wall time of a full-size
    ``plenopiv reconstruct`` (docs/performance.md). Here large arrays come from the heap, and
    up to :data:`KEEP_FREED_BYTES` of freed memory at its top is kept for the next ones: it
    stays resident, so a peak may grow by about that much (1 GB kept added 0.5 GB to the
    full-size benchmark's peak; 256 MB adds 0.08 GB and keeps most of the time saved).
    Called where :func:`prefer_small_pages` is. A ``MALLOC_MMAP_MAX_`` or
    ``MALLOC_TRIM_THRESHOLD_`` the user set is their choice and is left alone:
    ``user_environment`` holds those the user set (:func:`allocator_environment` pairs;
    default: this process's own). A batch worker is given its command's: a dask nanny
    starts every worker with ``MALLOC_TRIM_THRESHOLD_=65536`` (dask's choice, which made a
    full-size pair of ``plenopiv run`` a third slower). No change on a C library without
    ``mallopt`` (not glibc).

    Returns
    -------
    bool
        True when the allocator's settings were changed by this call.
    """
    chosen = allocator_environment() if user_environment is None else tuple(user_environment)
    if chosen:
        return False
    mallopt = _glibc("mallopt", (ctypes.c_int, ctypes.c_int))
    if mallopt is None:
        return False
    return bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, KEEP_FREED_BYTES))


def release_freed_memory() -> bool:
    """Hand the free memory inside this process's heap back to the system; True if called.

    glibc's ``malloc_trim``. With :func:`reuse_freed_memory` the freed arrays of one stage
    stay in the heap, holes included, for the next arrays; called where a stage of several GB
    begins (a volume's reconstruction), the holes the earlier stages left no longer add to
    its peak. Harmless in any process: it changes no setting, and a later array only faults
    its pages in again.
    """
    trim = _glibc("malloc_trim", (ctypes.c_size_t,))
    if trim is None:
        return False
    trim(0)
    return True


def own_process_memory(user_environment=None) -> None:
    """Set up the memory of a process that plenopiv owns: the command's, a batch worker's.

    :func:`prefer_small_pages` and :func:`reuse_freed_memory` (``user_environment``: the
    allocator variables the user set, for a batch worker its command's); not on import (a
    library does not change its caller's process).
    """
    prefer_small_pages()
    reuse_freed_memory(user_environment)


@functools.cache
def _glibc(name: str, argtypes: tuple):
    """The C function ``name`` of glibc with ``argtypes`` (ctypes); None on another C library."""
    if platform.libc_ver()[0] != "glibc":
        return None
    try:
        function = getattr(ctypes.CDLL(None), name)
    except (OSError, AttributeError):                   # pragma: no cover - not in this glibc
        return None
    function.argtypes = argtypes
    return function


def available_memory() -> int:
    """Memory available to this process now, bytes (``MemAvailable``; else physical)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not POSIX
        return 8 * 1024 ** 3


def format_bytes(n: float) -> str:
    """``n`` bytes as text (kB ... TiB)."""
    for unit, size in (("TiB", 1024 ** 4), ("GiB", 1024 ** 3), ("MiB", 1024 ** 2),
                       ("kiB", 1024)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{n:.0f} B"


def check_memory(nbytes: float, what: str, *, hint: str = "") -> None:
    """Raise :class:`ResourceError` when ``nbytes`` exceed the memory available now."""
    avail = available_memory()
    if nbytes > avail:
        raise ResourceError(f"{what} needs about {format_bytes(nbytes)} of memory but this "
                            f"machine has {format_bytes(avail)} available"
                            + (f": {hint}" if hint else ""))


def check_grid(grid, what: str = "the [volume] grid") -> None:
    """Refuse a reconstruction grid whose arrays alone would not fit in memory."""
    n = float(grid.shape[0]) * grid.shape[1] * grid.shape[2]
    check_memory(n * BYTES_PER_VOXEL,
                 f"{what} of {list(grid.shape)} = {n:.3g} voxels",
                 hint="use larger voxels (voxel_mm) or a smaller box")


def check_sensor(camera, what: str = "the camera's sensor") -> None:
    """Refuse a sensor whose images would not fit in memory."""
    rows, cols = camera.sensor.shape
    n = float(rows) * cols
    check_memory(n * BYTES_PER_PIXEL, f"{what} of {rows} × {cols} = {n:.3g} pixels",
                 hint="check [sensor] rows and cols")
