"""Output paths and atomic writes: a file is complete under its final name or absent.

A file is written under a temporary name in the same folder and renamed when complete, so a
crash never leaves a half-written product under the final name. Output paths are checked
before any work (:func:`check_output_path`); inputs are named as ``file.h5:/dataset`` or a
plain path (:func:`split_dataset_spec`).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from plenopiv.errors import ImageError, OutputError, WriteError
from plenopiv.products.locks import claim_output


def _file_mode() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


_FILE_MODE = _file_mode()


def _reason(exc: BaseException) -> str:
    """A short reason of a failed write (h5py folds errno into long RuntimeError texts)."""
    text = str(exc)
    if getattr(exc, "errno", None) == errno.ENOSPC or "No space left on device" in text \
            or "errno = 28" in text:
        return "no space left on device"
    if getattr(exc, "errno", None) == errno.EDQUOT or "Disk quota exceeded" in text:
        return "disk quota exceeded"
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror.lower()
    return (text.splitlines() or [type(exc).__name__])[0]


def write_failure(path: str | Path, exc: BaseException) -> WriteError:
    """The :class:`WriteError` for a write of ``path`` that raised ``exc``."""
    return WriteError(f"writing {str(path)!r} failed: {_reason(exc)} "
                      f"({type(exc).__name__}); nothing was written under that name")


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it to ``path`` if the block succeeds.

    The temporary is ``.NAME.XXXXXXXX.part`` in the same folder; it is deleted whatever
    happens. A write that fails with ``OSError`` (a full disk) becomes a
    :class:`~plenopiv.errors.WriteError` naming the path and the reason.
    """
    final = Path(path)
    if final.is_dir():
        raise OutputError(f"output {str(final)!r} is a folder: expected a file name")
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{final.name}.", suffix=".part", dir=final.parent)
        os.close(fd)
    except OSError as exc:
        raise OutputError(f"output {str(final)!r} cannot be written: {_reason(exc)}") from None
    tmp_path = Path(tmp)
    try:
        try:
            yield tmp_path
            os.chmod(tmp_path, _FILE_MODE)   # mkstemp makes 0600; give the usual permissions
            os.replace(tmp_path, final)
        except OSError as exc:
            raise write_failure(final, exc) from None
    finally:
        with contextlib.suppress(OSError):
            if tmp_path.exists():
                tmp_path.unlink()
        with contextlib.suppress(OSError):   # a writer that appends its own suffix (.vti)
            for extra in tmp_path.parent.glob(glob_escape(tmp_path.name) + ".*"):
                extra.unlink()


def glob_escape(name: str) -> str:
    """``name`` with the glob wildcards escaped."""
    import glob

    return glob.escape(name)


def check_output_path(path: str | Path, *, suffixes: tuple[str, ...] | None = None,
                      inputs=(), what: str = "--out", folder: bool = False) -> Path:
    """Check an output path before any work; return it.

    Refused (:class:`~plenopiv.errors.OutputError`, naming the path): a wrong suffix, an
    existing folder (or, with ``folder=True``, an existing file), something that is not a
    regular file (a device), one of the command's ``inputs`` (same resolved path or the same
    file through a link), a parent that is a file, and a folder where no file can be created
    (probed by creating and deleting a temporary file: read-only mounts, /proc, /sys, no
    permission), and anything inside the installed package (its presets and sources are
    never written). Nothing is left behind.

    Inside :func:`~plenopiv.products.locks.output_locks` (every ``plenopiv`` verb) the
    output is then locked until the verb ends: one another live process writes is refused
    (:class:`~plenopiv.products.locks.OutputLockedError`), a folder is created to hold its
    lock.
    """
    p = Path(path)
    if not str(path).strip():
        raise OutputError(f"{what} {str(path)!r}: expected a file name")
    if _inside_package(p):
        raise OutputError(f"{what} {str(path)!r} lies inside the installed plenopiv package "
                          f"({PACKAGE_DIR}): write it elsewhere (e.g. a copy of a preset to "
                          "edit: plenopiv presets NAME --out cam.toml)")
    if suffixes is not None and not folder and p.suffix.lower() not in suffixes:
        raise OutputError(f"{what} {str(path)!r}: expected a file ending in "
                          f"{' or '.join(suffixes)}")
    if folder:
        if p.exists() and not p.is_dir():
            raise OutputError(f"{what} {str(path)!r} is an existing file: expected a folder "
                              "(new or existing) for the products")
    elif p.is_dir():
        raise OutputError(f"{what} {str(path)!r} is a folder: expected a file name "
                          f"ending in {' or '.join(suffixes or ('the product suffix',))}")
    elif p.exists() and not p.is_file():
        raise OutputError(f"{what} {str(path)!r} exists and is not a regular file: expected "
                          "a new file or a product to replace")
    for inp in inputs:
        if inp is None:
            continue
        ip, _ = split_dataset_spec(inp)
        same = p.resolve() == ip.resolve()
        if not same and p.exists() and ip.exists():
            with contextlib.suppress(OSError):
                same = os.path.samefile(p, ip)
        if same:
            raise OutputError(f"{what} {str(path)!r} is the input {str(inp)!r}: it would be "
                              "overwritten; choose another output name")
    _probe_writable(p if folder else p.parent, what, str(path))
    claim_output(p, folder=folder, what=what)
    return p


#: The installed package's folder: nothing is ever written inside it.
PACKAGE_DIR = Path(__file__).resolve().parents[1]


def _inside_package(path: Path) -> bool:
    """Whether ``path`` (resolved through links) lies inside :data:`PACKAGE_DIR`."""
    try:
        return path.resolve().is_relative_to(PACKAGE_DIR)
    except (OSError, RuntimeError):
        return False


def _probe_writable(folder: Path, what: str, shown: str) -> None:
    target = folder
    while not target.exists():
        if target.parent == target:
            break
        target = target.parent
    if not target.is_dir():
        raise OutputError(f"{what} {shown!r}: {str(target)!r} is a file, not a folder")
    try:
        fd, tmp = tempfile.mkstemp(prefix=".plenopiv-probe.", suffix=".part", dir=target)
        os.close(fd)
        os.unlink(tmp)
    except OSError as exc:
        raise OutputError(f"{what} {shown!r}: cannot create files in {str(target)!r} "
                          f"({_reason(exc)}): expected a writable folder") from None


def file_identity(spec: str | Path) -> str:
    """Identity of an input file (or ``file.h5:/dataset``): its bytes' SHA-256 and the dataset.

    Two copies of one file are the same input; an edited or replaced file is another.
    """
    path, dataset = split_dataset_spec(spec)
    h = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    except OSError as exc:
        raise ImageError(f"input {str(path)!r} cannot be read: {_reason(exc)}") from None
    return h.hexdigest() + ("" if dataset is None else f":{dataset}")


def check_input_file(path: str | Path, what: str, error=None) -> Path:
    """``path`` as an existing regular file, else ``error`` (a PlenopivError class) naming it.

    A folder, a named pipe, a socket or a device is refused before it is opened: reading a
    pipe would wait for a writer that never comes.
    """
    from plenopiv.errors import ImageError

    error = ImageError if error is None else error
    p = Path(path)
    if not p.exists():
        raise error(f"{what} file {str(p)!r} not found")
    if p.is_dir():
        raise error(f"{what} file {str(p)!r} is a folder: expected a file")
    if not p.is_file():
        raise error(f"{what} file {str(p)!r} is not a regular file (a pipe, socket or "
                    "device): expected a file")
    return p


def split_dataset_spec(spec: str | Path) -> tuple[Path, str | None]:
    """Split ``file.h5:/path`` into the file and the dataset path (None for other files)."""
    s = str(spec)
    for suffix in (".h5:", ".hdf5:"):
        if suffix in s:
            i = s.index(suffix) + len(suffix) - 1
            return Path(s[:i]), s[i + 1:] or "/"
    return Path(s), None
