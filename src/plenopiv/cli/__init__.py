"""The ``plenopiv`` command (docs/cli.md). Every subcommand takes ``--json``.

Orchestration only: parse, validate, call the library, write products atomically, report.
One error path (:func:`main`, which lists the exit statuses): every failure is one line on
stderr, ``error: ...``, naming the thing, the value and what was expected, and with ``--json``
also one JSON object holding ``"error"`` on stdout. Arguments, output paths and sizes are
checked before the computation; no input file is ever overwritten. One module per
subcommand: ``add_parser(sub)`` builds its parser, ``cmd_<name>(args)`` runs it and returns
the summary, ``print_summary(summary)`` prints it for people; ``_common`` holds the parser
class, the shared options and the checks. Heavy libraries (dask, scipy, scikit-image, h5py)
are imported inside the commands.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shlex
import signal
import sys
import threading
import warnings

from plenopiv import __version__
from plenopiv.cli import (
    calibrate,
    compare,
    demo,
    piv,
    plan,
    presets,
    reconstruct,
    run,
    simulate,
    track,
    validate,
)
from plenopiv.cli._common import _add_example, _Parser
from plenopiv.cli._memory import out_of_memory
from plenopiv.cli._output import _fmt as _fmt
from plenopiv.cli._output import _print_lines
from plenopiv.cli._progress import _StageBar as _StageBar
from plenopiv.errors import (
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_TERMINATED,
    PlenopivError,
    PlenopivWarning,
    Terminated,
)
from plenopiv.products.jsonio import to_json
from plenopiv.products.locks import output_locks
from plenopiv.resources import own_process_memory

__all__ = ["build_parser", "main"]

#: The subcommands in the order ``plenopiv --help`` lists them; each adds its own parser.
COMMANDS = (demo, calibrate, reconstruct, piv, track, compare, plan, run, validate, simulate,
            presets)


def build_parser() -> argparse.ArgumentParser:
    """The ``plenopiv`` argument parser."""
    parser = _Parser(
        prog="plenopiv", description="Tomographic plenoptic PIV: simulate, calibrate, "
        "reconstruct and correlate.")
    parser.add_argument("--version", action="version", version=f"plenopiv {__version__}")
    _add_example(parser, "plenopiv demo --out demo_out")
    sub = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    return parser


def _print_human(summary: dict):
    """Print a command's summary for people (``--json`` prints it as it is)."""
    module = {c.__name__.rsplit(".", 1)[1]: c for c in COMMANDS}.get(summary.get("command"))
    getattr(module, "print_summary", _print_lines)(summary)


def _command_of(argv: list[str]) -> str | None:
    words = [a for a in argv if not a.startswith("-")]
    if not words:
        return None
    return " ".join(words[:2]) if words[0] == "simulate" and len(words) > 1 else words[0]


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _report_failure(exc: BaseException, status: int, command: str | None, as_json: bool,
                    warned: list[str]) -> int:
    """Print a failure the one way and return the exit status.

    An ``error:`` line on stderr and, with ``--json``, one JSON object holding ``"error"`` on
    stdout.
    """
    msg = _one_line(exc) or type(exc).__name__
    if as_json:
        obj = {**getattr(exc, "summary", {}), "command": command, "error": msg,
               "error_type": type(exc).__name__, "exit_status": status}
        if warned:
            obj["warnings"] = warned
        print(to_json(obj))
    print(f"error: {msg}", file=sys.stderr)
    return status


def _unexpected(exc: Exception) -> PlenopivError:
    """What to say of an exception plenopiv's own checks did not raise.

    Memory running out, in any of its shapes (:func:`~plenopiv.cli._memory.out_of_memory`);
    a read or write that failed; else a bug, with how to see where.
    """
    memory = out_of_memory(exc)
    if memory is not None:
        return memory
    if isinstance(exc, OSError):           # a read or write outside plenopiv's own checks
        where = f" ({exc.filename})" if exc.filename else ""
        return PlenopivError(f"a file operation failed{where}: {type(exc).__name__}: "
                             f"{_one_line(exc.strerror or exc)}")
    if os.environ.get("PLENOPIV_TRACEBACK"):
        import traceback

        traceback.print_exc()
    return PlenopivError(f"unexpected {type(exc).__name__}: {_one_line(exc)} (a bug in "
                         "plenopiv; set PLENOPIV_TRACEBACK=1 to see where)")


#: Seconds after a SIGTERM lost in a finalizer before the process sends itself another
SIGTERM_REPEAT_S = 0.05


#: Set once a SIGTERM has been taken: the process is ending (:func:`quiet_after_sigterm`).
SIGTERM_RECEIVED = threading.Event()


def quiet_after_sigterm(previous):
    """``sys.unraisablehook`` that drops what finalizers raise once SIGTERM was taken.

    A Terminated raised inside a compiled-code finalizer leaves its object half freed, and
    the object's next finalizer then fails (llvmlite: "no attribute '_as_parameter_'"),
    possibly after the command's one line is out; the process is ending with 143, and the
    failure is the signal's consequence, not news. Before that, ``previous`` takes them.
    """
    def hook(unraisable):
        if not SIGTERM_RECEIVED.is_set():
            previous(unraisable)
    return hook


class _Termination:
    """SIGTERM inside :func:`sigterm_as_interrupt`, and one that was lost.

    The handler raises :class:`~plenopiv.errors.Terminated` where the main thread happens to
    be. Raised inside a finalizer (numba's llvmlite frees its objects in ``__del__`` while
    compiling), Python prints it as an ignored exception and the command runs on; the
    unraisable hook (:meth:`unraisable`) takes it instead, and the process sends itself
    SIGTERM again after :data:`SIGTERM_REPEAT_S` (again if that one is lost too); a command
    that finishes before then ends as terminated all the same. A Terminated a verb catches
    on purpose (a batch that writes its summary) is its own: nothing is sent again.
    """

    def __init__(self):
        self.pending = False                # lost in a finalizer, not raised since
        self.answered = threading.Event()   # the command has stopped: nothing more is sent
        self.lock = threading.Lock()

    def handler(self, signum, frame):
        if self.answered.is_set():
            return
        SIGTERM_RECEIVED.set()
        self.pending = False
        raise Terminated()

    def unraisable(self, previous):
        """``sys.unraisablehook`` that keeps a lost Terminated, ``previous`` for the rest."""
        def hook(unraisable):
            if not isinstance(unraisable.exc_value, Terminated):
                previous(unraisable)
                return
            self.pending = True
            timer = threading.Timer(SIGTERM_REPEAT_S, self._again)
            timer.daemon = True
            timer.start()
        return hook

    def _again(self):
        with self.lock:
            if self.pending and not self.answered.is_set():
                os.kill(os.getpid(), signal.SIGTERM)

    def answer(self):
        """Nothing more is sent; one already sent is caught before the handler changes."""
        with self.lock:
            self.answered.set()


@contextlib.contextmanager
def sigterm_as_interrupt():
    """While inside, SIGTERM raises :class:`~plenopiv.errors.Terminated` (a KeyboardInterrupt).

    Every verb then stops on SIGTERM as on Ctrl-C, even where the first one is lost in a
    finalizer (:class:`_Termination`). Only in the main thread, where Python runs signal
    handlers; the previous handler comes back on leaving.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    termination = _Termination()
    previous, previous_hook = signal.getsignal(signal.SIGTERM), sys.unraisablehook
    signal.signal(signal.SIGTERM, termination.handler)
    sys.unraisablehook = termination.unraisable(previous_hook)
    try:
        yield
    finally:
        termination.answer()
        signal.signal(signal.SIGTERM, previous)
        sys.unraisablehook = previous_hook
        if termination.pending and sys.exc_info()[1] is None:    # finished after a lost one
            raise Terminated()


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``plenopiv`` command; returns the exit status.

    0: done. 1: a computation or a write failed (a full disk, failed pairs of ``run``, an
    unexpected error). 2: bad input, refused before any work. 130: interrupted (Ctrl-C).
    143: terminated (SIGTERM, as SLURM sends on a cancel or at the wall time), handled as
    Ctrl-C is: finished products kept, a batch's summary written.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    own_process_memory()            # the command owns its process
    as_json = "--json" in argv
    command = _command_of(argv)
    warned: list[str] = []

    def show(message, category, filename, lineno, file=None, line=None):
        text = _one_line(message)
        if text in warned:          # said already by this command (weights built twice ...)
            return
        warned.append(text)
        print(f"warning: {text}", file=sys.stderr)

    try:
        with warnings.catch_warnings(), sigterm_as_interrupt():
            warnings.simplefilter("always", PlenopivWarning)
            warnings.showwarning = show
            try:
                args = build_parser().parse_args(argv)
            except SystemExit as exc:          # --help, --version
                return exc.code if isinstance(exc.code, int) else 0
            command = args.command if args.command != "simulate" else f"simulate {args.kind}"
            as_json = bool(getattr(args, "json", as_json))
            with output_locks(shlex.join(["plenopiv", *argv])):
                summary = args.func(args)
    except PlenopivError as exc:
        return _report_failure(exc, exc.exit_status, command, as_json, warned)
    except KeyboardInterrupt as stop:
        return _stopped(stop, command, as_json, warned)
    except Exception as exc:  # noqa: BLE001 - the one error path: no traceback for users
        stop = _interrupt_within(exc)
        if stop is not None:
            return _stopped(stop, command, as_json, warned)
        return _report_failure(_unexpected(exc), EXIT_FAILED, command, as_json, warned)
    if warned:
        summary = {**summary, "warnings": warned}
    if as_json:
        print(to_json(summary))
    else:
        _print_human(summary)
    return 0


def _interrupt_within(exc: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C or SIGTERM that ``exc`` wraps, else None.

    Python wraps what some hooks raise: a SIGTERM that lands while a lazily imported module
    makes a class raises ``RuntimeError: Error calling __set_name__ ...`` with the Terminated
    as its cause. Followed through causes and contexts.
    """
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def _stopped(stop: KeyboardInterrupt, command, as_json: bool, warned) -> int:
    """The one line and the status of a command stopped by Ctrl-C (130) or SIGTERM (143)."""
    terminated = isinstance(stop, Terminated)
    exc = PlenopivError(f"{'terminated (SIGTERM)' if terminated else 'interrupted (Ctrl-C)'}"
                        "; products written so far are complete, temporaries are removed "
                        "on the next run")
    return _report_failure(exc, EXIT_TERMINATED if terminated else EXIT_INTERRUPTED,
                           command, as_json, warned)


def console() -> None:
    """The ``plenopiv`` command: :func:`main`, its status the process's exit status.

    Ended by SIGTERM or Ctrl-C, the process leaves at once once its one line is out: the
    interpreter's finalizers would run compiled-code destructors half torn down by the
    signal (numba's llvmlite prints an ignored exception then), and would wait for the kernel
    threads of :func:`plenopiv._threads.run_slices`, one of which may wait on a lock the
    interrupted thread never released.
    """
    import os

    sys.unraisablehook = quiet_after_sigterm(sys.unraisablehook)
    status = main()
    if status in (EXIT_TERMINATED, EXIT_INTERRUPTED):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
    sys.exit(status)


if __name__ == "__main__":  # pragma: no cover
    console()
