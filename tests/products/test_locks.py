"""One writer per output (plenopiv.products.locks), for every verb that writes.

The table :data:`WRITERS` names every writing verb (``simulate`` kind by kind) and the output
it locks; a test checks that it holds every verb of the command but the two that write
nothing. Each writer is then run through ``main``: a live holder of its output is refused
with its PID, host and start time; a dead holder's lock is taken over with a warning and the
lock is released whatever ends the verb (an error, Ctrl-C, SIGTERM). The cheap writers also
run to success, and every writer is stopped by a real SIGTERM in a process of its own.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import plenopiv.products.files as files
from plenopiv.calibration.model import Calibration
from plenopiv.camera.corrections import DepthCorrection
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import load_camera
from plenopiv.cli import COMMANDS, build_parser, main
from plenopiv.cli.simulate import KINDS
from plenopiv.errors import ComputationError, Terminated
from plenopiv.products import locks
from plenopiv.products.locks import (
    FOLDER_LOCK_NAME,
    OutputLock,
    OutputLockedError,
    claim_output,
    holder_record,
    lock_file,
    output_locks,
    read_lock,
    stale_reason,
)
from plenopiv.products.volume import VolumeResult
from small_case import VOLUME, simulate_pair_argv

REPO = Path(__file__).resolve().parents[2]

EXPERIMENT = """camera = "small_m1"
""" + VOLUME + """[piv]
windows = [[12, 12, 12]]
passes = 2
uncertainty = "correlation"
[images]
pairs = "pairs/*.h5"
calibration = "cal.h5"
dt_s = 1e-3
[output]
directory = "{out}"
png = false
vtk = false
weights_cache = ""
"""

#: Every verb that writes, the arguments that make it write (``{d}``: the inputs, ``{o}``: an
#: output folder) and the output it locks (``/`` at the end: a folder of products).
WRITERS = {
    "demo": ("demo --out {o}/demo", "{o}/demo/"),
    "validate": ("validate oseen --out {o}/val", "{o}/val/"),
    "run": ("run {d}/run.toml", "{o}/batch/"),
    "calibrate": ("calibrate small_m1 --focal-point {d}/fp.tif --out {o}/cal.h5",
                  "{o}/cal.h5"),
    "reconstruct": ("reconstruct {d}/cal.h5 {d}/pairs/p_1.h5:/image_a --config {d}/exp.toml "
                    "--out {o}/v.h5", "{o}/v.h5"),
    "piv": ("piv {d}/va.h5 {d}/vb.h5 --out {o}/w.h5", "{o}/w.h5"),
    "track": ("track {d}/cal.h5 {d}/pairs/p_1.h5:/image_a {d}/pairs/p_1.h5:/image_b "
              "--config {d}/exp.toml --out {o}/t.h5", "{o}/t.h5"),
    "presets": ("presets small_m1 --out {o}/cam.toml", "{o}/cam.toml"),
    **{f"simulate {kind}": (f"simulate {kind} small_test --out {{o}}/x."
                            + ("h5" if kind == "pair" else "tif"),
                            "{o}/x." + ("h5" if kind == "pair" else "tif"))
       for kind, _ in KINDS},
}
#: The verbs that write nothing.
NON_WRITERS = {"compare", "plan"}


def volume(path: Path, shape, seed):
    """A random volume with a particle table of one particle per 8 voxels (a vector needs
    ``[piv] min_particles_per_window`` of them in its window)."""
    grid = VolumeGrid((0.0, 0.0, 0.0), (1e-4, 1e-4, 1e-4), shape)
    rng = np.random.default_rng(seed)
    vol = rng.random(shape).astype(np.float32)
    n = int(np.prod(shape)) // 8
    pos = rng.uniform(0.0, 1e-4, (n, 3)) * np.array(shape[::-1])
    VolumeResult(vol, grid, DepthCorrection(1.0, 1.0), pos, pos, np.ones(n),
                 np.full((n, 3), 1e-4)).save(path)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A calibration, a focal-point image, two simulated pairs, volumes, an experiment."""
    d = tmp_path_factory.mktemp("inputs")
    Calibration.from_camera(load_camera("small_m1")).save(d / "cal.h5")
    assert main(["simulate", "focal-point", "small_m1", "--out", str(d / "fp.tif"),
                 "--quiet", "--json"]) == 0
    for i in (1, 2, 3):
        assert main(simulate_pair_argv(d / "pairs" / f"p_{i}.h5", seed=i, n_particles=40)
                    + ["--quiet", "--json"]) == 0
    volume(d / "va.h5", (8, 10, 12), 1)
    volume(d / "vb.h5", (8, 10, 12), 2)
    volume(d / "big_a.h5", (64, 64, 64), 3)
    volume(d / "big_b.h5", (64, 64, 64), 4)
    (d / "exp.toml").write_text(EXPERIMENT.format(out="out"))
    # a box that keeps reconstruct busy for seconds, so that a SIGTERM finds it at work
    (d / "exp_big.toml").write_text(EXPERIMENT.format(out="out").replace(
        "x_mm = [-1.0625, 1.0625]", "x_mm = [-2.5, 2.5]").replace(
        "y_mm = [-1.0625, 1.0625]", "y_mm = [-2.5, 2.5]"))
    return d


def argv_of(verb: str, d: Path, o: Path, inputs_dir: Path) -> tuple[list[str], Path, bool]:
    """The arguments of ``verb``, its locked output and whether that is a folder."""
    text, out = WRITERS[verb]
    if verb == "run":
        (inputs_dir / "run.toml").write_text(EXPERIMENT.format(out=str(o / "batch")))
    args = [a.replace("{d}", str(d)).replace("{o}", str(o)) for a in text.split()]
    folder = out.endswith("/")
    return args, Path(out.rstrip("/").replace("{o}", str(o))), folder


@pytest.fixture(scope="module")
def live_holder():
    """Another live process on this host, and a lock record naming it."""
    proc = subprocess.Popen(["sleep", "600"])
    yield holder_record("plenopiv run other.toml", pid=proc.pid)
    proc.kill()
    proc.wait()


def dead_record() -> dict:
    proc = subprocess.Popen(["true"])
    proc.wait()
    return holder_record("plenopiv run earlier.toml", pid=proc.pid)


def plant(output: Path, folder: bool, record: dict) -> Path:
    """Write the lock of ``output`` holding ``record``; return the lock file."""
    path = lock_file(output, folder=folder)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record))
    return path


def verbs_of_the_command() -> set[str]:
    """Every verb of ``plenopiv``, ``simulate`` kind by kind."""
    names = {c.__name__.rsplit(".", 1)[1] for c in COMMANDS} - {"simulate"}
    return names | {f"simulate {k}" for k, _ in KINDS}


def test_the_table_names_every_verb_that_writes():
    """Every verb with an ``--out`` (and ``run``, which writes its ``[output] directory``) is
    in WRITERS; the others are the verbs that write nothing."""
    assert set(WRITERS) | NON_WRITERS == verbs_of_the_command()
    assert not set(WRITERS) & NON_WRITERS
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    for name, parser in sub.choices.items():
        kinds = next((a.choices for a in parser._actions if a.dest == "kind"), None)
        for verb, p in ((f"{name} {k}", q) for k, q in kinds.items()) if kinds else [
                (name, parser)]:
            has_out = any("--out" in a.option_strings for a in p._actions)
            assert (verb in WRITERS) == (has_out or verb == "run"), verb


@pytest.mark.parametrize("verb", sorted(WRITERS))
def test_a_live_holder_is_refused_with_its_pid_host_and_start(verb, inputs, tmp_path,
                                                              live_holder, capsys):
    args, out, folder = argv_of(verb, inputs, tmp_path, inputs)
    path = plant(out, folder, live_holder)
    before = sorted(p.name for p in tmp_path.rglob("*"))
    assert main(args) == 2
    err = capsys.readouterr().err
    line = next(ln for ln in err.splitlines() if ln.startswith("error: "))
    assert f"PID {live_holder['pid']} on host {socket.gethostname()}" in line
    assert live_holder["started"] in line and "plenopiv run other.toml" in line
    assert "Traceback" not in err
    assert read_lock(path) == live_holder                  # the holder's lock is left alone
    assert sorted(p.name for p in tmp_path.rglob("*")) == before


class Stop(Exception):
    """Raised right after a verb took its lock."""


def wrapped(stop: BaseException) -> RuntimeError:
    """What Python raises when a signal lands in a class's making (a lazy import): the stop
    as the cause of a RuntimeError."""
    exc = RuntimeError("Error calling __set_name__ on 'Field' instance '_shared' in "
                       "'ProjectionGeometry'")
    exc.__cause__ = stop
    return exc


STOPS = {"error": (ComputationError("stopped after the lock"), 1, "stopped after the lock"),
         "ctrl-c": (KeyboardInterrupt(), 130, "interrupted (Ctrl-C)"),
         "sigterm": (Terminated(), 143, "terminated (SIGTERM)"),
         "ctrl-c in an import": (wrapped(KeyboardInterrupt()), 130, "interrupted (Ctrl-C)"),
         "sigterm in an import": (wrapped(Terminated()), 143, "terminated (SIGTERM)")}


@pytest.mark.parametrize("stop", sorted(STOPS))
@pytest.mark.parametrize("verb", sorted(WRITERS))
def test_a_dead_holder_is_taken_over_and_the_lock_released_whatever_stops(
        verb, stop, inputs, tmp_path, monkeypatch, capsys):
    """The verb takes the lock of a dead process over (a warning names it) and is stopped
    right after: the lock is gone afterwards, and a folder made for it too."""
    args, out, folder = argv_of(verb, inputs, tmp_path, inputs)
    dead = dead_record()
    path = plant(out, folder, dead)
    exc, status, said = STOPS[stop]
    real = files.claim_output
    taken = []

    def claim_then_stop(output, **kwargs):
        real(output, **kwargs)
        taken.extend(locks.held_locks())
        raise exc

    monkeypatch.setattr(files, "claim_output", claim_then_stop)
    assert main(args) == status
    err = capsys.readouterr().err
    assert f"took over the lock left by PID {dead['pid']}" in err
    assert "is no longer running" in err and said in err and "Traceback" not in err
    assert path in taken and not path.exists() and not locks.held_locks()


@pytest.mark.parametrize("verb", sorted(WRITERS))
def test_a_folder_made_for_a_lock_is_removed_when_nothing_was_written(verb, inputs, tmp_path,
                                                                       monkeypatch):
    args, out, folder = argv_of(verb, inputs, tmp_path / "new", inputs)
    real = files.claim_output

    def claim_then_stop(output, **kwargs):
        real(output, **kwargs)
        assert lock_file(output, folder=kwargs.get("folder", False)).exists()
        raise Stop

    monkeypatch.setattr(files, "claim_output", claim_then_stop)
    assert main(args) == 1
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize("verb", ["presets", "piv", "simulate dark"])
def test_a_writer_that_succeeds_releases_its_lock(verb, inputs, tmp_path, capsys):
    args, out, folder = argv_of(verb, inputs, tmp_path, inputs)
    args += {"simulate dark": ["--lenslets", "5", "7", "--frames", "1"],
             "piv": ["--windows", "8", "8", "8", "--no-vtk", "--no-png"]}.get(verb, [])
    path = plant(out, folder, dead_record())
    assert main(args + ["--quiet"]) == 0, capsys.readouterr().err
    assert out.exists() and not path.exists()
    assert not list(tmp_path.rglob("*.lock"))


# ---- the lock itself -----------------------------------------------------------------------


def test_stale_or_live_by_host_pid_and_age(tmp_path, live_holder):
    path = tmp_path / ".x.h5.lock"
    path.write_text("{}")
    assert stale_reason(live_holder, path) is None
    assert "no longer running" in stale_reason(dead_record(), path)
    reused = {**live_holder, "pid_start": (live_holder["pid_start"] or 0) + 1}
    assert "belongs to another process" in stale_reason(reused, path)
    remote = {**live_holder, "host": "node-elsewhere", "pid": 1}
    assert stale_reason(remote, path) is None                 # fresh: its holder may live
    old = time.time() - locks.STALE_AFTER_S - 5
    os.utime(path, (old, old))
    assert "last refreshed" in stale_reason(remote, path)
    assert "unreadable" in stale_reason(None, path)
    os.utime(path)
    assert stale_reason(None, path) is None                   # being written right now


def test_a_lock_replaced_by_another_is_not_removed_by_its_old_holder(tmp_path):
    lock = OutputLock(tmp_path / "x.h5").acquire()
    other = holder_record("plenopiv piv ...")
    lock.path.write_text(json.dumps(other))
    assert not lock.refresh()
    lock.release()
    assert read_lock(lock.path) == other


@pytest.mark.parametrize("at", ["file made", "record half written"])
def test_a_stop_inside_the_taking_of_a_lock_leaves_no_lock(tmp_path, monkeypatch, at):
    """SIGTERM lands between creating the lock file and noting it held, or while its record
    is written: nothing is left that would refuse the next run."""
    real, write = locks._create, os.write

    def made_then_stopped(path, record):
        real(path, record)
        raise Terminated()

    def stopped_writing(fd, data):
        raise Terminated()

    if at == "file made":
        monkeypatch.setattr(locks, "_create", made_then_stopped)
    else:
        monkeypatch.setattr(locks.os, "write", stopped_writing)
    with pytest.raises(Terminated), output_locks():
        claim_output(tmp_path / "x.h5")
    monkeypatch.setattr(locks.os, "write", write)
    assert list(tmp_path.iterdir()) == []


def test_the_heartbeat_keeps_a_remote_lock_fresh(tmp_path, monkeypatch):
    monkeypatch.setattr(locks, "HEARTBEAT_S", 0.05)
    with output_locks("plenopiv run x.toml"):
        claim_output(tmp_path / "x.h5")
        path = lock_file(tmp_path / "x.h5")
        old = time.time() - 3600
        os.utime(path, (old, old))
        deadline = time.time() + 10
        while path.stat().st_mtime < old + 1 and time.time() < deadline:
            time.sleep(0.02)
        assert path.stat().st_mtime > time.time() - 60
    assert not path.exists()


def test_outside_a_scope_nothing_is_locked(tmp_path):
    assert files.check_output_path(tmp_path / "x.h5", suffixes=(".h5",)) == tmp_path / "x.h5"
    assert list(tmp_path.iterdir()) == []


def test_a_file_inside_a_folder_another_process_writes_is_refused(tmp_path, live_holder):
    plant(tmp_path / "batch", True, live_holder)
    with output_locks(), pytest.raises(OutputLockedError, match=r"lies in the folder .*PID"):
        claim_output(tmp_path / "batch" / "p_vectors.h5")
    with output_locks():                         # this process's own folder: allowed
        claim_output(tmp_path / "mine", folder=True)
        claim_output(tmp_path / "mine" / "p_vectors.h5")
        assert len(locks.held_locks()) == 2
    assert not (tmp_path / "mine").exists()


def _race(path: str, barrier, results) -> None:
    import warnings

    warnings.simplefilter("ignore")              # the takeover's warning, in a child
    try:
        barrier.wait()
        with output_locks():
            claim_output(path)
            results.put("took")
            time.sleep(1.0)
    except OutputLockedError:
        results.put("refused")


@pytest.mark.parametrize("stale", [False, True])
def test_of_processes_racing_for_one_output_exactly_one_writes(tmp_path, stale):
    """Six processes at once, on a free output or on one whose holder died: one takes it."""
    ctx = multiprocessing.get_context("fork")
    out = tmp_path / "x.h5"
    if stale:
        plant(out, False, dead_record())
    barrier, results = ctx.Barrier(6), ctx.Queue()
    procs = [ctx.Process(target=_race, args=(str(out), barrier, results))
             for _ in range(6)]
    for p in procs:
        p.start()
    got = sorted(results.get(timeout=60) for _ in procs)
    for p in procs:
        p.join(timeout=60)
    assert got == ["refused"] * 5 + ["took"]
    assert not lock_file(out).exists()


# ---- SIGTERM, for real ---------------------------------------------------------------------

#: Verbs stopped by a real SIGTERM while they work, with the changes that keep them busy:
#: ``(replace, by)`` in their arguments, and more arguments.
SIGTERM_VERBS = {
    "calibrate": ((), []), "reconstruct": (("/exp.toml", "/exp_big.toml"), []),
    "track": ((), []), "demo": ((), []),
    "validate": ((), []), "run": ((), []), "simulate focal-point": ((), []),
    "piv": (("/va.h5", "/big_a.h5", "/vb.h5", "/big_b.h5"), []),
    "simulate pair": ((), ["--n-particles", "20000"]),
}


def cli_env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO / "src"), str(REPO),
                                         env.get("PYTHONPATH", "")])
    return env


def start(args: list[str], cwd: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "plenopiv.cli", *args, "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=cli_env(), cwd=cwd, start_new_session=True)


def wait_for(path: Path, proc: subprocess.Popen, seconds: float = 120) -> None:
    deadline = time.time() + seconds
    while not path.exists():
        if proc.poll() is not None or time.time() > deadline:
            raise AssertionError(f"{path} never appeared: {proc.communicate(timeout=30)}")
        time.sleep(0.02)


@pytest.mark.parametrize("verb", sorted(SIGTERM_VERBS))
def test_sigterm_stops_every_writer_with_143_one_line_and_its_lock_released(verb, inputs,
                                                                          tmp_path):
    assert set(SIGTERM_VERBS) <= set(WRITERS)
    args, out, folder = argv_of(verb, inputs, tmp_path, inputs)
    swaps, more = SIGTERM_VERBS[verb]
    for old, new in zip(swaps[::2], swaps[1::2], strict=True):
        args = [a.replace(old, new) for a in args]
    proc = start(args + more, tmp_path)
    path = lock_file(out, folder=folder)
    wait_for(path, proc)
    os.kill(proc.pid, signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143, (stdout, stderr)
    assert "error: terminated (SIGTERM)" in stderr and "Traceback" not in stderr
    assert not path.exists()
    assert not list(tmp_path.rglob(".*.part"))


def test_two_runs_into_one_folder_the_second_refused_and_sigterm_mid_batch(inputs, tmp_path,
                                                                           capsys):
    """The issue's case: a second ``plenopiv run`` with other settings into the folder a first
    one writes is refused with the first one's PID; the first, stopped by SIGTERM while its
    LocalCluster computes, ends with 143 and one line, writes its summary (finished pairs
    done, the others interrupted), leaves no temporary and releases its lock; a rerun
    resumes."""
    first = inputs / "run_first.toml"
    first.write_text(EXPERIMENT.format(out=str(tmp_path / "batch")))
    second = inputs / "run_second.toml"
    second.write_text(EXPERIMENT.format(out=str(tmp_path / "batch")).replace(
        "passes = 2", "passes = 1"))
    proc = start(["run", str(first), "--workers", "1"], tmp_path)
    lock = tmp_path / "batch" / FOLDER_LOCK_NAME
    wait_for(lock, proc)
    assert main(["run", str(second), "--workers", "1"]) == 2
    err = capsys.readouterr().err
    assert f"PID {proc.pid} on host {socket.gethostname()}" in err and "run_first.toml" in err
    wait_for(tmp_path / "batch" / "p_1_vectors.h5", proc, seconds=300)
    time.sleep(0.5)                                   # p_1 reported done by now
    os.kill(proc.pid, signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143, (stdout, stderr)
    said = [ln for ln in stderr.splitlines() if not ln.startswith("warning: ")]
    assert len(said) == 1, stderr                          # one line: no worker logs either
    assert said[0].startswith("error: terminated (SIGTERM) after "), stderr
    summary = json.loads((tmp_path / "batch" / "batch_summary.json").read_text())
    assert "p_1" in summary["done"] and summary["n_interrupted"] >= 1
    assert summary["n_done"] + summary["n_interrupted"] == 3
    assert not lock.exists() and not list((tmp_path / "batch").glob(".*.part"))
    assert main(["run", str(first), "--workers", "1", "--json", "--quiet"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert set(again["skipped"]) >= set(summary["done"])    # a pair finishing as the batch
    assert sorted(again["skipped"] + again["done"]) == ["p_1", "p_2", "p_3"]  # stopped: kept


def test_a_run_stopped_while_it_prepares_writes_its_summary(inputs, tmp_path, monkeypatch,
                                                           capsys):
    """SIGTERM before the pairs start (weights, response): the summary is this run's, every
    pair interrupted, and the lock released."""
    import plenopiv.workflow.worker as worker

    exp = inputs / "run_prepare.toml"
    exp.write_text(EXPERIMENT.format(out=str(tmp_path / "batch")))
    (tmp_path / "batch").mkdir()
    (tmp_path / "batch" / "batch_summary.json").write_text('{"from": "an earlier run"}')

    def terminated(*args, **kwargs):
        raise Terminated()

    monkeypatch.setattr(worker, "prepare_weights", terminated)
    assert main(["run", str(exp), "--json"]) == 143
    out = json.loads(capsys.readouterr().out)
    assert out["exit_status"] == 143 and out["n_interrupted"] == 3
    summary = json.loads((tmp_path / "batch" / "batch_summary.json").read_text())
    assert summary["interrupted"] == ["p_1", "p_2", "p_3"] and summary["n_done"] == 0
    assert not (tmp_path / "batch" / FOLDER_LOCK_NAME).exists()


def test_the_heartbeat_does_not_stop_rehearsals_from_forking(tmp_path):
    """The background compilation forks while a verb holds its locks (the heartbeat thread
    runs then), as it did before locks existed; it spawns only for threads that matter."""
    code = ("from plenopiv.products.locks import output_locks, claim_output\n"
            "from plenopiv.workflow.precompile import can_fork\n"
            "import threading\n"
            f"with output_locks():\n    claim_output({str(tmp_path / 'x.h5')!r})\n"
            "    print(can_fork())\n"
            "    threading.Thread(target=threading.Event().wait, args=(2,), daemon=True)"
            ".start()\n    print(can_fork())\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=cli_env(), timeout=120, check=True).stdout.split()
    assert out == ["True", "False"]


#: Files written beside a verb's ``--out``: each is locked as the output itself is.
BESIDE = {"calibrate": "{o}/cal.png", "piv": "{o}/w.vti", "track": "{o}/t_binned.h5",
          "simulate pair": "{o}/x_A.tif"}


@pytest.mark.parametrize("verb", sorted(BESIDE))
def test_the_files_written_beside_an_output_are_locked_too(verb, inputs, tmp_path,
                                                           live_holder, capsys):
    args, _, _ = argv_of(verb, inputs, tmp_path, inputs)
    plant(Path(BESIDE[verb].replace("{o}", str(tmp_path))), False, live_holder)
    assert main(args) == 2
    assert f"PID {live_holder['pid']}" in capsys.readouterr().err
