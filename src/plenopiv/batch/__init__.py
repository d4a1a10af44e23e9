"""Many image pairs on dask: a local process pool, a SLURM allocation or an existing scheduler.

A batch is a list of :class:`PairJob` (two images in, one HDF5 product out) and a ``process``
function that turns one job into its product. :func:`run_batch` sends the jobs to dask worker
processes, shows a progress bar, records every failure with its reason and goes on with the
rest, and writes ``batch_summary.json`` beside the products. It is resumable: a job whose
product is complete (:func:`is_complete`) and was made from the same inputs is skipped. The
contract ``process`` must keep (atomic writes, the completeness mark, the identity, what it
returns) and how failures and worker deaths are handled are in the Notes of
:func:`run_batch`. This is the only module that imports dask, inside the functions that need
it, so that ``import plenopiv.batch`` stays cheap.
"""

from __future__ import annotations

import contextlib
import glob
import json
import os
import sys
import time
import traceback as tb
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from plenopiv.batch.cluster import (
    _LOCAL_OPTIONS,
    _SLURM_OPTIONS,
    CONNECT_TIMEOUT_S,
    THREAD_ENV_VARS,
    _check_options,
    _cluster_kind,
    _import_jobqueue,
    _local_size,
    _open_client,
    _positive_int,
    batch_options,
    probe_scheduler,
    slurm_cluster_kwargs,
    thread_env,
)
from plenopiv.batch.jobs import (
    COMPLETE_ATTR,
    IDENTITY_ATTR,
    PairJob,
    _remove_stale_parts,
    _stale_reason,
    discover_pairs,
    finished_before,
    is_complete,
    lost_reason,
    mark_complete,
    product_identity,
)
from plenopiv.errors import (
    EXIT_INTERRUPTED,
    EXIT_TERMINATED,
    ConfigError,
    PlenopivError,
    Terminated,
)
from plenopiv.products.files import atomic_path
from plenopiv.products.jsonio import dumps, to_json

__all__ = [
    "COMPLETE_ATTR",
    "SUMMARY_NAME",
    "THREAD_ENV_VARS",
    "IDENTITY_ATTR",
    "BatchError",
    "BatchInterrupted",
    "BatchSummary",
    "JobResult",
    "PairJob",
    "batch_options",
    "check_batch_options",
    "discover_pairs",
    "is_complete",
    "mark_complete",
    "pending_jobs",
    "product_identity",
    "run_batch",
    "slurm_cluster_kwargs",
    "stopped_before_start",
    "thread_env",
]

#: File name of the batch summary written in the output folder.
SUMMARY_NAME = "batch_summary.json"



class BatchError(PlenopivError):
    """A batch job broke the contract of :func:`run_batch` (e.g. its product is not complete)."""


class BatchInterrupted(PlenopivError):
    """The batch was stopped by Ctrl-C or SIGTERM; its summary was written, a rerun resumes.

    ``summary`` holds :meth:`BatchSummary.to_dict` of the pairs finished before the stop.
    """

    exit_status = EXIT_INTERRUPTED

    def __init__(self, message: str, summary: dict, *, terminated: bool = False):
        super().__init__(message)
        self.summary = summary
        if terminated:
            self.exit_status = EXIT_TERMINATED


# ---- results -------------------------------------------------------------------------------


@dataclass(frozen=True)
class JobResult:
    """What became of one job.

    status : "done" | "skipped" (complete product found) | "failed" | "interrupted" (not
    finished when the batch was stopped).
    seconds : time in ``process`` (wall clock, s); ``start``/``end`` are epoch seconds.
    result : the dict ``process`` returned (None unless done).
    error_type, error, traceback : the failure (None unless failed).
    worker, pid : the dask worker address and process id that ran it.
    """

    name: str
    status: str
    output: str
    seconds: float = 0.0
    result: dict | None = None
    error_type: str | None = None
    error: str | None = None
    traceback: str | None = None
    worker: str | None = None
    pid: int | None = None
    start: float | None = None
    end: float | None = None

    def to_dict(self, *, tracebacks: bool = True) -> dict:
        """JSON-friendly values (the traceback left out unless ``tracebacks``)."""
        d = {k: getattr(self, k) for k in ("name", "status", "output", "seconds", "result",
                                           "error_type", "error", "worker", "pid", "start",
                                           "end")}
        if tracebacks:
            d["traceback"] = self.traceback
        return d


@dataclass(frozen=True)
class BatchSummary:
    """The outcome of :func:`run_batch`.

    done, skipped : names of the pairs computed now / found complete.
    failed : ``(name, "ErrorType: message")`` of each failed pair.
    recomputed : ``(name, reason)`` of each complete product found made from other settings
        or inputs, and recomputed (its pair is also in ``done`` or ``failed``).
    interrupted : names of the pairs not finished when the batch was stopped (Ctrl-C).
    seconds : wall-clock time of the whole batch (s), cluster start and stop included.
    results : one :class:`JobResult` per job, in the order of the jobs.
    """

    done: tuple[str, ...]
    skipped: tuple[str, ...]
    failed: tuple[tuple[str, str], ...]
    seconds: float
    results: tuple[JobResult, ...] = field(repr=False)
    cluster: str = "local"
    n_workers: int | None = None
    threads_per_worker: int | None = None
    removed_parts: tuple[str, ...] = ()
    summary_path: str | None = None
    recomputed: tuple[tuple[str, str], ...] = ()
    interrupted: tuple[str, ...] = ()

    @property
    def n_jobs(self) -> int:
        """Number of jobs in the batch."""
        return len(self.results)

    @property
    def ok(self) -> bool:
        """True when no pair failed and none was left unfinished."""
        return not self.failed and not self.interrupted

    def result(self, name: str) -> JobResult:
        """Return the result of the pair ``name``."""
        for r in self.results:
            if r.name == name:
                return r
        raise KeyError(name)

    def to_dict(self, *, tracebacks: bool = False) -> dict:
        """Return a one-object summary for ``--json`` (tracebacks only on request).

        Plain JSON types only: numpy values become numbers and lists, anything else that a
        ``process`` returned becomes its ``repr``.
        """
        from plenopiv import __version__
        from plenopiv.products.provenance import schema_version

        d = {"schema_version": schema_version("batch summary"), "plenopiv_version": __version__,
             "n_jobs": self.n_jobs, "n_done": len(self.done),
             "n_skipped": len(self.skipped), "n_failed": len(self.failed),
             "done": list(self.done), "skipped": list(self.skipped),
             "failed": [{"name": n, "error": e} for n, e in self.failed],
             "n_recomputed": len(self.recomputed),
             "recomputed": [{"name": n, "reason": r} for n, r in self.recomputed],
             "n_interrupted": len(self.interrupted), "interrupted": list(self.interrupted),
             "seconds": round(self.seconds, 3), "cluster": self.cluster,
             "n_workers": self.n_workers, "threads_per_worker": self.threads_per_worker,
             "removed_parts": list(self.removed_parts), "summary_path": self.summary_path,
             "results": [r.to_dict(tracebacks=tracebacks) for r in self.results]}
        return json.loads(dumps(d, default=_json_default))


def _run_job(process: Callable[[PairJob], Any], job: PairJob,
             threads: int | None = None) -> JobResult:
    """Run ``process(job)`` on a worker; an exception becomes a failed result (not retried)."""
    pid = os.getpid()
    worker = None
    with contextlib.suppress(Exception):
        from distributed import get_worker

        worker = get_worker().address
    _limit_numba_threads(threads)
    start = time.time()
    t0 = time.perf_counter()
    try:
        out = process(job)
        out = {} if out is None else out
        if not isinstance(out, Mapping):
            raise BatchError(f"process returned a {type(out).__name__}: expected a dict (or "
                             "None)")
        if not is_complete(job.output):
            raise BatchError(f"process returned but {str(job.output)!r} is not a complete "
                             f"product: write it atomically and call mark_complete() last "
                             f"(root attribute {COMPLETE_ATTR!r} = True)")
        if job.identity is not None and product_identity(job.output) != dict(job.identity):
            raise BatchError(f"process returned but {str(job.output)!r} does not record the "
                             f"job's identity (root attribute {IDENTITY_ATTR!r}): "
                             "mark_complete(path, identity=job.identity)")
        return JobResult(job.name, "done", str(job.output), time.perf_counter() - t0,
                         result=dict(out), worker=worker, pid=pid, start=start, end=time.time())
    except (Exception, SystemExit) as exc:  # noqa: BLE001 - a failed pair is recorded, not fatal
        return JobResult(job.name, "failed", str(job.output), time.perf_counter() - t0,
                         error_type=type(exc).__name__, error=str(exc),
                         traceback=tb.format_exc(), worker=worker, pid=pid, start=start,
                         end=time.time())


def _limit_numba_threads(threads: int | None) -> None:
    """Hold numba to ``threads`` threads in this worker even if it was imported too early.

    The Nanny sets NUMBA_NUM_THREADS in a worker before the worker imports anything, but a
    spawned worker first re-imports the user's ``__main__`` module; when that imports numba,
    numba has read the variable before it was set (and re-reads it only when it compiles, not
    when it loads a cached kernel).
    """
    numba = sys.modules.get("numba")
    if numba is None or threads is None:
        return
    try:
        numba.core.config.reload_config()
    except RuntimeError:
        # its threads already run with another count: keep the environment consistent with
        # that, or numba's next compilation would raise the same error inside `process`
        os.environ["NUMBA_NUM_THREADS"] = str(numba.config.NUMBA_NUM_THREADS)
    with contextlib.suppress(Exception):
        if numba.get_num_threads() > threads:
            numba.set_num_threads(threads)   # per thread: this task's thread runs the kernels


def _lost_result(job: PairJob, exc: BaseException, retries: int | None) -> JobResult:
    """Describe a job whose task itself erred (its worker died, it was cancelled ...)."""
    from distributed import KilledWorker

    if isinstance(exc, KilledWorker):
        times = f"{retries + 1} times" if retries is not None else "repeatedly"
        msg = (f"the worker process running this pair died {times} (a crash in compiled "
               f"code, os._exit, or killed for using too much memory); see the worker logs. "
               f"{exc}")
    else:
        msg = str(exc) or repr(exc)
    return JobResult(job.name, "failed", str(job.output), error_type=type(exc).__name__,
                     error=msg, traceback="".join(tb.format_exception(exc)))


# ---- the batch -----------------------------------------------------------------------------


def _check_jobs(jobs) -> tuple[PairJob, ...]:
    jobs = tuple(jobs)
    if not jobs:
        raise ConfigError("no pairs to process: the job list is empty (check the image "
                          "patterns)")
    bad = [j for j in jobs if not isinstance(j, PairJob)]
    if bad:
        raise ConfigError(f"jobs must be PairJob objects, got a {type(bad[0]).__name__}")
    for attr in ("name", "output"):
        seen: set = set()
        for j in jobs:
            v = getattr(j, attr) if attr == "name" else j.output.resolve()
            if v in seen:
                raise ConfigError(f"two jobs have the same {attr} {str(v)!r}: each pair needs "
                                  f"its own {attr}")
            seen.add(v)
    return jobs


def _check_process(process) -> None:
    if not callable(process):
        raise ConfigError(f"process {process!r} is not callable: expected a function "
                          "process(job) -> dict")
    import cloudpickle

    try:
        cloudpickle.dumps(process)
    except Exception as exc:  # noqa: BLE001 - any pickling failure is the same user error
        raise ConfigError(f"process {process!r} cannot be sent to worker processes "
                          f"({type(exc).__name__}: {exc}); use a top-level function of an "
                          "importable module") from None


def _json_default(obj):
    """JSON for numpy values and paths; anything else a ``process`` returned as its repr."""
    try:
        return json.loads(to_json(obj))
    except TypeError:
        return repr(obj)


def _default_summary_path(jobs: Sequence[PairJob]) -> Path:
    parents = {str(j.output.resolve().parent) for j in jobs}
    return Path(os.path.commonpath(sorted(parents))) / SUMMARY_NAME


def check_batch_options(*, cluster: str = "local", n_workers: int | None = None,
                        threads_per_worker: int | None = None, retries: int = 2,
                        cluster_options: Mapping | None = None,
                        connect_timeout: float = CONNECT_TIMEOUT_S) -> None:
    """Check the cluster options of :func:`run_batch` without starting anything.

    A command can then refuse them before its own long preparations; a scheduler address
    must answer as a dask scheduler within ``connect_timeout`` seconds
    (:func:`~plenopiv.batch.cluster.probe_scheduler`).
    """
    kind = _cluster_kind(cluster)
    _positive_int(n_workers, "n_workers")
    _positive_int(threads_per_worker, "threads_per_worker")
    _positive_int(retries, "retries", allow_none=False, minimum=0)
    allowed = {"local": _LOCAL_OPTIONS, "slurm": _SLURM_OPTIONS}.get(kind, ())
    _check_options(cluster_options, allowed, kind)
    _check_timeout(connect_timeout)
    if kind == "address":
        probe_scheduler(cluster, connect_timeout)


def _check_timeout(value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not 0 < value < float("inf"):
        raise ConfigError(f"connect_timeout {value!r}: expected a finite number of seconds > 0")
    return float(value)


def run_batch(jobs: Sequence[PairJob], process: Callable[[PairJob], dict], *,
              cluster: str = "local", n_workers: int | None = None,
              threads_per_worker: int | None = None, resume: bool = True, retries: int = 2,
              progress: bool = True, cluster_options: Mapping | None = None,
              summary_path: str | Path | None = None,
              connect_timeout: float = CONNECT_TIMEOUT_S) -> BatchSummary:
    """Run ``process`` on every job on dask worker processes; resumable and fault tolerant.

    Parameters
    ----------
    jobs : sequence of PairJob
        Unique names, unique outputs (see :func:`discover_pairs`).
    process : callable
        ``process(job) -> dict``, a picklable top-level function that writes ``job.output``
        atomically and marks it complete (the contract is in the Notes).
    cluster : str
        ``"local"``: a ``LocalCluster`` of worker processes on this machine; ``"slurm"``: a
        dask-jobqueue ``SLURMCluster`` (``pip install plenopiv[hpc]``); or the address of a
        running scheduler (``"tcp://host:8786"``), whose workers are used as they are.
    n_workers : int, optional
        Worker processes (local; default: the cores // ``threads_per_worker``). For SLURM,
        the number of SLURM jobs is ``cluster_options["jobs"]`` or enough for ``n_workers``.
    threads_per_worker : int, optional
        Cores each worker process uses for its pair (default: cores // ``n_workers``, at
        least 1; both default to one single-threaded worker per core). A worker runs ONE pair
        at a time, and ``NUMBA_NUM_THREADS``, ``OMP_NUM_THREADS``, ``MKL_NUM_THREADS`` and
        ``OPENBLAS_NUM_THREADS`` are set to this in the worker processes, so that workers ×
        threads never exceeds the cores. Not applied to the workers of a scheduler address.
    resume : bool
        Skip jobs whose product :func:`is_complete` and records the job's ``identity``
        (default True; a product made from other settings or inputs is recomputed, see
        Notes). ``False`` recomputes all. Either way, the ``.part`` temporaries beside the
        products are deleted first: run one batch per output folder at a time.
    retries : int
        How many more times a job is run after the worker process running it died (default
        2). Exceptions raised by ``process`` are deterministic and are not retried. With a
        scheduler address the scheduler's own ``allowed-failures`` applies instead.
    progress : bool
        A progress bar (and one line per failure) on stderr.
    cluster_options : mapping, optional
        Local: ``memory_limit``, ``dashboard_address`` (default ":0", a free port),
        ``local_directory``. SLURM: see :func:`slurm_cluster_kwargs` (the ``[batch]`` table;
        :func:`batch_options` maps it).
    summary_path : str or Path, optional
        Where to write the JSON summary (default: ``batch_summary.json`` in the products'
        common folder). Written atomically, failures included.
    connect_timeout : float
        Seconds a scheduler address has to answer as one (else a ``ConfigError``).

    Returns
    -------
    BatchSummary

    Raises
    ------
    ConfigError
        For bad arguments, before anything runs or is deleted.
    BatchInterrupted
        On Ctrl-C (KeyboardInterrupt): the cluster is closed, the summary (pairs finished so
        far; the others ``interrupted``) is written, and a rerun resumes.

    Notes
    -----
    The contract of ``process`` (atomic writes, the completeness mark, the identity that
    resume checks) and how failures and worker deaths are retried are in docs/batch.md
    ("The contract of a batch's work").
    """
    jobs = _check_jobs(jobs)
    _check_process(process)
    kind, n_workers, threads, retries, options, slots = _cluster_plan(
        cluster, n_workers, threads_per_worker, retries, cluster_options, connect_timeout)
    summary_file = Path(summary_path) if summary_path else _default_summary_path(jobs)

    t0 = time.perf_counter()
    removed = _remove_temporaries(jobs, summary_file)
    results, recomputed, todo = _jobs_to_run(jobs, resume, finished_before(summary_file))
    interrupted = None
    try:
        if todo:
            with _open_client(kind, cluster, n_workers, threads, retries, options,
                              connect_timeout) as client:
                _submit_and_collect(client, todo, process, results,
                                    threads=threads if kind != "address" else None,
                                    slots=slots, retries=retries, progress=progress,
                                    total=len(jobs), skipped=len(jobs) - len(todo),
                                    known_retries=kind != "address")
    except KeyboardInterrupt as exc:       # Ctrl-C, or SIGTERM (errors.Terminated)
        interrupted = exc
    for job in jobs:
        if job.name not in results:
            results[job.name] = JobResult(job.name, "interrupted", str(job.output))
    if interrupted:          # a write killed part way leaves a temporary: remove it now
        removed += _remove_stale_parts(jobs)
    summary = _write_summary(
        tuple(results[j.name] for j in jobs), summary_file, seconds=time.perf_counter() - t0,
        cluster=cluster, n_workers=n_workers, threads_per_worker=threads,
        removed_parts=tuple(str(p) for p in removed), recomputed=tuple(recomputed))
    if interrupted is not None:
        raise _interruption(interrupted, summary, summary_file)
    return summary


def stopped_before_start(jobs: Sequence[PairJob], stop: KeyboardInterrupt, *,
                         resume: bool = True, summary_path: str | Path | None = None
                         ) -> BatchInterrupted:
    """The :class:`BatchInterrupted` of a batch stopped while it prepared, its summary written.

    A command that prepares before :func:`run_batch` (weights, the response) calls this on a
    Ctrl-C or SIGTERM, so that ``batch_summary.json`` describes this run, not an earlier one:
    pairs whose complete product was made with their identity are ``skipped`` (jobs
    without an identity are not checked), every other ``interrupted``.
    """
    jobs = _check_jobs(jobs)
    summary_file = Path(summary_path) if summary_path else _default_summary_path(jobs)
    known = resume and all(j.identity is not None for j in jobs)
    results, recomputed, _ = _jobs_to_run(jobs, known)
    for job in jobs:
        results.setdefault(job.name, JobResult(job.name, "interrupted", str(job.output)))
    summary = _write_summary(tuple(results[j.name] for j in jobs), summary_file, seconds=0.0,
                             recomputed=tuple(recomputed))
    return _interruption(stop, summary, summary_file)


def _interruption(stop: KeyboardInterrupt, summary, summary_file) -> BatchInterrupted:
    """The :class:`BatchInterrupted` of a batch stopped by Ctrl-C or SIGTERM."""
    terminated = isinstance(stop, Terminated)
    by = "terminated (SIGTERM)" if terminated else "interrupted (Ctrl-C)"
    return BatchInterrupted(
        f"{by} after {len(summary.done)} of {summary.n_jobs} pairs "
        f"({len(summary.interrupted)} not finished, {len(summary.failed)} failed); "
        f"summary written to {summary_file}; run the same command again to resume",
        summary.to_dict(), terminated=terminated)


def _write_summary(ordered: tuple[JobResult, ...], summary_file: Path, **fields
                   ) -> BatchSummary:
    """The :class:`BatchSummary` of the results (in job order), written atomically as JSON."""
    summary = BatchSummary(
        done=tuple(r.name for r in ordered if r.status == "done"),
        skipped=tuple(r.name for r in ordered if r.status == "skipped"),
        failed=tuple((r.name, f"{r.error_type}: {r.error}") for r in ordered
                     if r.status == "failed"),
        results=ordered, summary_path=str(summary_file),
        interrupted=tuple(r.name for r in ordered if r.status == "interrupted"), **fields)
    with atomic_path(summary_file) as tmp:
        tmp.write_text(dumps(summary.to_dict(tracebacks=True), indent=1) + "\n")
    return summary


def _cluster_plan(cluster: str, n_workers, threads_per_worker, retries, cluster_options,
                  connect_timeout=CONNECT_TIMEOUT_S) -> tuple:
    """Checked cluster options of :func:`run_batch` (``connect_timeout`` checked, not kept).

    Returns ``(kind, n_workers, threads, retries, options, slots)``; ``slots`` is the number
    of pairs run at once when known before the cluster starts (else None).
    """
    kind = _cluster_kind(cluster)
    _check_timeout(connect_timeout)
    slots = None
    n_workers = _positive_int(n_workers, "n_workers")
    threads = _positive_int(threads_per_worker, "threads_per_worker")
    retries = _positive_int(retries, "retries", allow_none=False, minimum=0)
    if kind == "local":
        n_workers, threads = _local_size(n_workers, threads)
        options = _check_options(cluster_options, _LOCAL_OPTIONS, kind)
        slots = n_workers
    elif kind == "slurm":
        options = _check_options(cluster_options, _SLURM_OPTIONS, kind)
        _import_jobqueue()
        kw, n_jobs = slurm_cluster_kwargs(options, threads_per_worker=threads,
                                          n_workers=n_workers)
        threads = threads or max(1, kw["job_cpu"] // kw["processes"])
        slots = n_jobs * kw["processes"]
    else:
        options = _check_options(cluster_options, (), kind)
    return kind, n_workers, threads, retries, options, slots


def _remove_temporaries(jobs: Sequence[PairJob], summary_file: Path) -> list[Path]:
    """Delete the ``.part`` temporaries of the products and of the summary; return them."""
    removed = _remove_stale_parts(jobs)
    for p in summary_file.parent.glob(f".{glob.escape(summary_file.name)}.*.part"):
        with contextlib.suppress(FileNotFoundError):
            p.unlink()
            removed.append(p)
    return removed


def pending_jobs(jobs: Sequence[PairJob], *, resume: bool = True) -> list[PairJob]:
    """The jobs :func:`run_batch` would run now: what a command prepares for beforehand.

    With ``resume``, those without a complete product made with their identity; else all.
    """
    return _jobs_to_run(_check_jobs(jobs), resume)[2]


def _jobs_to_run(jobs: Sequence[PairJob], resume: bool,
                 finished: set[str] = frozenset()) -> tuple[dict, list, list]:
    """``(results of the skipped jobs, (name, why) of the recomputed ones, jobs to run)``.

    With ``resume``, a complete product made with the job's identity is skipped; one made
    with other settings or inputs, or missing a companion file, is recomputed, with the
    reason; so is a pair the earlier summary records as ``finished`` whose product is gone.
    """
    results: dict[str, JobResult] = {}
    recomputed: list[tuple[str, str]] = []
    todo = []
    for job in jobs:
        if resume and is_complete(job.output):
            reason = _stale_reason(job)
            if reason is None:
                results[job.name] = JobResult(job.name, "skipped", str(job.output))
                continue
            recomputed.append((job.name, reason))
        elif resume and job.name in finished:
            recomputed.append((job.name, lost_reason(job)))
        todo.append(job)
    return results, recomputed, todo


def _worker_slots(client, requested: int | None) -> int:
    """Pairs the cluster can run at once: the size asked for, else its worker threads now.

    The size asked for wins where known (local and SLURM): a SLURM cluster whose jobs are
    still queued reports fewer workers than it will have, and the client's view of the
    workers briefly holds both the dead and the restarted one after a worker dies.
    """
    if requested:
        return requested
    info = client.scheduler_info()
    return max(1, sum(w.get("nthreads", 1) for w in info.get("workers", {}).values()))


def _submit_and_collect(client, todo: Sequence[PairJob], process,
                        results: dict[str, JobResult], *, threads: int | None,
                        slots: int | None, retries: int, progress: bool, total: int, skipped: int,
                        known_retries: bool) -> dict[str, JobResult]:
    """Run ``todo`` on the cluster, filling ``results`` as pairs finish.

    A Ctrl-C then leaves the finished ones in it.
    """
    from distributed import as_completed
    from tqdm import tqdm

    token = uuid.uuid4().hex[:8]
    by_key = {}

    def submit(job: PairJob):
        # retries=0: an error that escapes _run_job (a task that cannot even be unpickled on
        # the worker) is as deterministic as one inside `process`; a worker that dies is
        # another matter, handled by the scheduler's allowed-failures (= `retries`)
        fut = client.submit(_run_job, process, job, threads, key=f"pair-{job.name}-{token}",
                            pure=False, retries=0)
        by_key[fut.key] = job
        return fut

    # At most one pair in flight per worker slot. The scheduler would otherwise send every
    # task to a worker at once (small task groups are not queued on the scheduler), and a
    # pair waiting behind a crashing one on the same worker would be charged for its deaths.
    pending = list(reversed(todo))
    in_flight = as_completed(loop=client.loop)

    def top_up():
        while pending and in_flight.count() < _worker_slots(client, slots):
            in_flight.add(submit(pending.pop()))

    top_up()
    n_failed = 0
    # disable=None: the bar shows on a terminal only, never in a redirected log
    with tqdm(total=total, initial=skipped, desc="plenopiv batch", unit="pair",
              disable=None if progress else True, file=sys.stderr, leave=False,
              dynamic_ncols=True) as bar:
        for fut in in_flight:
            job = by_key.pop(fut.key)
            try:
                res = fut.result()
            except Exception as exc:  # noqa: BLE001 - the task erred outside `process`
                res = _lost_result(job, exc, retries if known_retries else None)
            fut.release()
            top_up()
            results[job.name] = res
            if res.status == "failed":
                n_failed += 1
                bar.set_postfix(failed=n_failed)
                if progress:
                    bar.write(f"failed {job.name}: {res.error_type}: {res.error}",
                              file=sys.stderr)
            bar.update(1)
    return results
