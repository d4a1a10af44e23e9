"""Out of memory in every shape it reaches the command: one message, with the figures.

Memory runs out as a :class:`MemoryError` (NumPy says how much it asked for), but also as an
``OSError`` ENOMEM, a shared library that fails to map ("failed to map segment", an
``ImportError``), or a thread that cannot start (its stack is address space): under an
address-space limit (``ulimit -v``, a batch system's memory limit) the last two come first.
:func:`out_of_memory` recognises them and says how much was asked, the limit and what is free.
"""

from __future__ import annotations

import errno
import resource

from plenopiv.errors import ResourceError

#: Words of the messages that memory exhaustion takes outside a MemoryError (lower case)
SIGNS = ("cannot allocate memory", "failed to map segment", "out of memory",
         "can't start new thread", "std::bad_alloc", "unable to allocate", "mmap failed")


def _is_memory(exc: BaseException) -> bool:
    if isinstance(exc, MemoryError):
        return True
    if isinstance(exc, OSError) and exc.errno == errno.ENOMEM:
        return True
    return any(sign in str(exc).lower() for sign in SIGNS)


def _chain(exc: BaseException):
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        yield exc
        exc = exc.__cause__ or exc.__context__


def _limit_text() -> str:
    """The address-space limit and the free memory, as figures for the message."""
    from plenopiv.resources import available_memory, format_bytes

    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    free = f"{format_bytes(available_memory())} of memory is available"
    if soft == resource.RLIM_INFINITY:
        return free
    return (f"this process may use {format_bytes(soft)} of address space (ulimit -v "
            f"{soft // 1024}); {free}")


def out_of_memory(exc: BaseException) -> ResourceError | None:
    """The error to report when ``exc`` (or what caused it) is memory running out, else None."""
    found = next((e for e in _chain(exc) if _is_memory(e)), None)
    if found is None:
        return None
    said = " ".join(str(found).split()) or "no memory left"
    return ResourceError(
        f"out of memory ({type(found).__name__}: {said}); {_limit_text()}: raise the limit "
        "(ulimit -v, the batch system's memory request) or use a smaller [volume], sensor or "
        "batch (plenopiv plan estimates the memory a run needs)")
