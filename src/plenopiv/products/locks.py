"""One writer per output: a lock file taken when a command checks its output, before any work.

A file output ``DIR/NAME`` is locked by ``DIR/.NAME.lock``, a folder of products (a batch, a
demo, a study) by ``FOLDER/.plenopiv.lock``; each holds JSON naming its holder (PID, host,
start time, command). A second writer is refused with the holder (:class:`OutputLockedError`);
a lock whose holder is gone (dead PID on this host, or a lock from another host not refreshed
for :data:`STALE_AFTER_S`) is taken over with a warning. Locks are taken inside
:func:`output_locks` (the ``plenopiv`` command opens it around every verb) and all released
when it closes, also on an error, Ctrl-C or SIGTERM. docs/cli.md ("One writer per output").
"""

from __future__ import annotations

import contextlib
import json
import os
import shlex
import socket
import sys
import threading
import time
import uuid
import warnings
from collections.abc import Iterator
from pathlib import Path

from plenopiv.errors import OutputError, PlenopivWarning
from plenopiv.products.jsonio import dumps

#: The lock of a folder of products, inside it.
FOLDER_LOCK_NAME = ".plenopiv.lock"
#: How often a holder refreshes the modification time of its locks, seconds.
HEARTBEAT_S = 30.0
#: A lock from another host whose file was not refreshed for this long is stale, seconds.
STALE_AFTER_S = 600.0
#: An unreadable lock younger than this is being written by its holder, seconds.
WRITING_GRACE_S = 10.0
#: The name of the thread that refreshes this process's locks.
HEARTBEAT_THREAD = "plenopiv-lock-heartbeat"


class OutputLockedError(OutputError):
    """Another live process writes this output (refused before any work, exit status 2)."""


def lock_file(path: str | Path, *, folder: bool = False) -> Path:
    """The lock file of the output ``path`` (a file, or with ``folder=True`` a folder)."""
    p = Path(path)
    return p / FOLDER_LOCK_NAME if folder else p.with_name(f".{p.name}.lock")


def _boot_id() -> str | None:
    with contextlib.suppress(OSError):
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    return None


def _process_start(pid: int) -> int | None:
    """When process ``pid`` started, clock ticks since boot (Linux); None where unknown.

    A live PID with another start time is another process that reused the PID.
    """
    try:
        stat = Path(f"/proc/{int(pid)}/stat").read_text()
        return int(stat.rsplit(")", 1)[1].split()[19])
    except (OSError, ValueError, IndexError):
        return None


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return True           # a process of another user, or a PID this system cannot hold
    return True


def holder_record(command: str | None = None, *, pid: int | None = None) -> dict:
    """What a lock file holds about its holder (this process unless ``pid``)."""
    pid = os.getpid() if pid is None else int(pid)
    now = time.time()
    return {"pid": pid, "host": socket.gethostname(), "boot_id": _boot_id(),
            "pid_start": _process_start(pid),
            "started": time.strftime("%Y-%m-%d %H:%M:%S %z", time.localtime(now)),
            "started_s": now, "command": command or shlex.join(sys.argv),
            "token": uuid.uuid4().hex}


def read_lock(path: Path) -> dict | None:
    """The record of the lock file ``path``; None where it is missing or unreadable."""
    try:
        rec = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return rec if isinstance(rec, dict) and "pid" in rec and "host" in rec else None


def stale_reason(record: dict | None, path: Path) -> str | None:
    """Why the lock ``path`` with ``record`` has no live holder; None while it has one."""
    try:
        age = time.time() - path.stat().st_mtime
    except OSError:
        return "it is gone"
    if record is None:
        return (f"its file is unreadable and {age:.0f} s old" if age > WRITING_GRACE_S
                else None)
    same_machine = (record.get("host") == socket.gethostname()
                    and record.get("boot_id") == _boot_id())
    if same_machine:
        pid = record.get("pid")
        if not isinstance(pid, int) or not _pid_alive(pid):
            return f"process {pid} is no longer running"
        start = _process_start(pid)
        if record.get("pid_start") is not None and start is not None \
                and start != record["pid_start"]:
            return f"process {pid} is no longer running (its PID belongs to another process)"
        return None
    if age > STALE_AFTER_S:
        return (f"it was last refreshed {age:.0f} s ago on host {record.get('host')} (a live "
                f"holder refreshes it every {HEARTBEAT_S:.0f} s; stale after "
                f"{STALE_AFTER_S:.0f} s)")
    return None


def describe_holder(record: dict | None) -> str:
    """The holder of a lock in words: PID, host, start time and command."""
    if record is None:
        return "a process whose lock file is still being written"
    return (f"PID {record.get('pid')} on host {record.get('host')}, started "
            f"{record.get('started')} ({record.get('command')})")


def _create(path: Path, record: dict) -> bool:
    """Create the lock file ``path`` holding ``record``; False where it exists."""
    try:
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        return False
    try:
        os.write(fd, (dumps(record) + "\n").encode())
    except BaseException:                    # a stop (or a full disk) half way: no torso left
        os.close(fd)
        with contextlib.suppress(OSError):
            path.unlink()
        raise
    os.close(fd)
    return True


def _take_over(path: Path, seen: dict | None) -> bool:
    """Remove the stale lock ``path`` whose record was ``seen``; False where it changed.

    One taker at a time: a ``.takeover`` file created exclusively guards the check and the
    removal, so that two processes taking over the same stale lock cannot remove each
    other's new one.
    """
    guard = path.with_name(path.name + ".takeover")
    if not _create(guard, {"pid": os.getpid(), "host": socket.gethostname()}):
        with contextlib.suppress(OSError):
            if time.time() - guard.stat().st_mtime > WRITING_GRACE_S:
                guard.unlink()                       # its taker died within the takeover
        return False
    try:
        if read_lock(path) != seen:
            return False
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
        return True
    finally:
        with contextlib.suppress(OSError):
            guard.unlink()


class OutputLock:
    """The lock of one output, held by this process (:meth:`acquire`, :meth:`release`)."""

    def __init__(self, output: str | Path, *, folder: bool = False, command: str | None = None,
                 what: str = "output"):
        self.output, self.folder, self.what = Path(output), folder, what
        self.path = lock_file(output, folder=folder)
        self.record = holder_record(command)
        self.held = False
        self.created: list[Path] = []                # folders made here, outermost first

    def acquire(self) -> OutputLock:
        """Take the lock; a stale one is taken over with a warning.

        Raises
        ------
        OutputLockedError
            A live process holds it: its PID, host, start time and command are named.
        """
        self._make_folder()
        try:
            return self._take()
        except BaseException:
            self._remove_made_folders()
            raise

    def _take(self) -> OutputLock:
        for _ in range(5):
            try:
                if _create(self.path, self.record):
                    self.held = True
                    return self
            except OSError as exc:
                raise OutputError(f"{self.what} {str(self.output)!r}: its lock "
                                  f"{str(self.path)!r} cannot be created "
                                  f"({exc.strerror or exc})") from None
            seen = read_lock(self.path)
            if seen is None and not self.path.exists():
                continue                                 # released meanwhile
            reason = stale_reason(seen, self.path)
            if reason is None:
                self._refuse(seen)
            if _take_over(self.path, seen):
                left = describe_holder(seen) if seen else "an unreadable lock file"
                warnings.warn(f"{self.what} {str(self.output)!r}: took over the lock left by "
                              f"{left}: {reason}", PlenopivWarning, stacklevel=2)
            else:
                time.sleep(0.05)
        self._refuse(read_lock(self.path))

    def _make_folder(self) -> None:
        """Create the lock's folder and its missing parents, remembered to remove if unused.

        The output folder of a folder, the folder an output file goes in otherwise.
        """
        missing = []
        p = self.path.parent
        while not p.exists() and p.parent != p:
            missing.append(p)
            p = p.parent
        for folder in reversed(missing):
            try:
                folder.mkdir()
            except FileExistsError:
                continue
            except OSError as exc:
                raise OutputError(f"{self.what} {str(self.output)!r} cannot be created: "
                                  f"{exc.strerror or exc}") from None
            self.created.append(folder)

    def _refuse(self, seen: dict | None):
        raise OutputLockedError(
            f"{self.what} {str(self.output)!r} is being written by another plenopiv process: "
            f"{describe_holder(seen)}; wait for it to end or stop it (its lock is "
            f"{str(self.path)!r}; a lock whose process is gone is taken over by the next run, "
            f"one from another host after {STALE_AFTER_S / 60:.0f} minutes without refresh, "
            "or delete it once that process is surely gone)")

    def refresh(self) -> bool:
        """Touch the lock file (the heartbeat); False where it is no longer this process's."""
        if not self.held or read_lock(self.path) != self.record:
            return False
        with contextlib.suppress(OSError):
            os.utime(self.path)
        return True

    def release(self) -> None:
        """Remove the lock file if it is still this process's; an empty folder made here too.

        Whether it is this process's is read from the file (its record), so a stop between
        creating the file and noting it held still removes it.
        """
        if self.record["pid"] != os.getpid():
            return
        self.held = False
        if read_lock(self.path) == self.record:
            with contextlib.suppress(OSError):
                self.path.unlink()
        self._remove_made_folders()

    def _remove_made_folders(self) -> None:
        for folder in reversed(self.created):
            try:
                folder.rmdir()                       # only where nothing was written
            except OSError:
                break
        self.created = []


class _Scope:
    """The locks taken inside one :func:`output_locks`, and their heartbeat."""

    def __init__(self, command: str | None):
        self.command = command
        self.locks: dict[Path, OutputLock] = {}
        self.stop = threading.Event()
        self.beat: threading.Thread | None = None

    def claim(self, output: Path, folder: bool, what: str) -> OutputLock:
        key = lock_file(output, folder=folder).resolve()
        if key in self.locks:
            return self.locks[key]
        if not folder:
            self._refuse_inside_locked_folder(output, what)
        lock = OutputLock(output, folder=folder, command=self.command, what=what)
        self.locks[key] = lock                   # released on leaving, however acquire ends
        try:
            lock.acquire()
        except OutputError:
            del self.locks[key]
            raise
        if self.beat is None:
            self.beat = threading.Thread(target=self._heartbeat, name=HEARTBEAT_THREAD,
                                         daemon=True)
            self.beat.start()
        return lock

    def _refuse_inside_locked_folder(self, output: Path, what: str) -> None:
        """A file inside a folder that another live process (a batch) holds is refused."""
        folder_lock = lock_file(output.parent, folder=True)
        if folder_lock.resolve() in self.locks or not folder_lock.exists():
            return
        seen = read_lock(folder_lock)
        if stale_reason(seen, folder_lock) is None:
            raise OutputLockedError(
                f"{what} {str(output)!r} lies in the folder {str(output.parent)!r}, which "
                f"another plenopiv process writes: {describe_holder(seen)}; wait for it to "
                "end or write elsewhere")

    def _heartbeat(self) -> None:
        while not self.stop.wait(HEARTBEAT_S):
            for lock in list(self.locks.values()):
                lock.refresh()

    def close(self) -> None:
        self.stop.set()
        for lock in reversed(list(self.locks.values())):
            lock.release()
        self.locks.clear()


_SCOPES: list[_Scope] = []


@contextlib.contextmanager
def output_locks(command: str | None = None) -> Iterator[None]:
    """Inside, :func:`claim_output` locks outputs; all are released on leaving, whatever ends it.

    ``command`` is what the lock files name as their holder's command (default: this
    process's arguments).
    """
    scope = _Scope(command)
    _SCOPES.append(scope)
    try:
        yield
    finally:
        _SCOPES.remove(scope)
        scope.close()


def claim_output(output: str | Path, *, folder: bool = False, what: str = "output") -> None:
    """Lock ``output`` until the innermost :func:`output_locks` closes; nothing outside one.

    Raises :class:`OutputLockedError` where another live process holds it, or (for a file)
    holds the folder it lies in.
    """
    if _SCOPES:
        _SCOPES[-1].claim(Path(output), folder, what)


def held_locks() -> list[Path]:
    """The lock files this process holds now (innermost scope last)."""
    return [lock.path for scope in _SCOPES for lock in scope.locks.values()]
