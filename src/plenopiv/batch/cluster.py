"""The dask side of :mod:`plenopiv.batch`: cluster options, clients, worker thread pools.

A ``"local"`` cluster of worker processes, a SLURM cluster (dask-jobqueue), or the address
of a running scheduler; each worker's numba/BLAS/OpenMP threads pinned to
``threads_per_worker``. dask is imported inside the functions that need it.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

from plenopiv.errors import ConfigError

#: Environment variables that set the thread pools of numba and the BLAS/OpenMP libraries.
THREAD_ENV_VARS = ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS",
                   "OPENBLAS_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")
_CLUSTER_KINDS = ("local", "slurm")
_ADDRESS = re.compile(r"^(?:(?:tcp|tls|inproc|ucx|ws|wss)://\S+|[\w.\-]+:\d+)$")
_LOCAL_OPTIONS = ("memory_limit", "dashboard_address", "local_directory")
_SLURM_OPTIONS = ("queue", "account", "cores", "processes", "memory", "walltime", "jobs",
                  "job_extra_directives", "job_script_prologue", "local_directory",
                  "log_directory", "interface", "python")


def thread_env(threads: int) -> dict[str, str]:
    """Return the environment giving numba, OpenMP and BLAS ``threads`` threads each."""
    return {k: str(int(threads)) for k in THREAD_ENV_VARS}


def _cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def _cluster_kind(cluster: str) -> str:
    if not isinstance(cluster, str):
        raise ConfigError(f"cluster {cluster!r}: expected 'local', 'slurm' or a scheduler "
                          "address such as 'tcp://host:8786'")
    if cluster in _CLUSTER_KINDS:
        return cluster
    if _ADDRESS.match(cluster):
        return "address"
    raise ConfigError(f"cluster {cluster!r}: expected 'local', 'slurm' or a scheduler address "
                      "such as 'tcp://host:8786'")


def _positive_int(value, what: str, *, allow_none: bool = True, minimum: int = 1):
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ConfigError(f"{what} {value!r}: expected an integer >= {minimum}")
    return value


def _local_size(n_workers, threads) -> tuple[int, int]:
    cores = _cores()
    if n_workers is None and threads is None:
        return cores, 1
    if n_workers is None:
        return max(1, cores // threads), threads
    if threads is None:
        return n_workers, max(1, cores // n_workers)
    return n_workers, threads


def _check_options(options: Mapping | None, allowed: tuple[str, ...], kind: str) -> dict:
    opts = {k: v for k, v in dict(options or {}).items() if v is not None}
    unknown = sorted(set(opts) - set(allowed))
    if unknown:
        raise ConfigError(f"cluster_options for cluster={kind!r}: unknown key "
                          f"{unknown[0]!r}; expected some of {', '.join(allowed)}")
    return opts


def slurm_cluster_kwargs(options: Mapping | None, *, threads_per_worker: int | None = None,
                         n_workers: int | None = None) -> tuple[dict, int]:
    """Map the ``[batch]`` SLURM settings to ``dask_jobqueue.SLURMCluster`` keywords.

    Each SLURM job books ``cores`` CPUs and ``memory`` and runs ``processes`` dask worker
    processes (default ``cores // threads_per_worker``), each running one pair at a time with
    ``threads_per_worker`` numba/BLAS threads (exported in the job script).

    Parameters
    ----------
    options : mapping
        ``queue`` (partition), ``account``, ``cores`` (CPUs per SLURM job), ``processes``
        (worker processes per job), ``memory`` (per job, e.g. ``"64GB"``), ``walltime``
        (``"HH:MM:SS"``), ``jobs`` (number of SLURM jobs, default: enough for ``n_workers``
        workers, else 1), and passed through to dask-jobqueue: ``job_extra_directives``,
        ``job_script_prologue``, ``local_directory``, ``log_directory``, ``interface``,
        ``python``. ``cores`` and ``memory`` may come from dask's ``jobqueue.slurm`` config
        instead.
    threads_per_worker, n_workers : int, optional
        As for :func:`run_batch`.

    Returns
    -------
    kwargs : dict
        Keywords of ``SLURMCluster``.
    jobs : int
        The number of SLURM jobs to start (``cluster.scale(jobs=jobs)``).
    """
    import dask

    opts = _check_options(options, _SLURM_OPTIONS, "slurm")
    cores = opts.pop("cores", None) or dask.config.get("jobqueue.slurm.cores", None)
    memory = opts.pop("memory", None) or dask.config.get("jobqueue.slurm.memory", None)
    if cores is None or memory is None:
        raise ConfigError("cluster='slurm' needs [batch] cores (CPUs per SLURM job) and memory "
                          "(per SLURM job, e.g. memory = \"64GB\")")
    cores = _positive_int(cores, "[batch] cores", allow_none=False)
    try:
        dask.utils.parse_bytes(memory)
    except (ValueError, TypeError):
        raise ConfigError(f"[batch] memory {memory!r}: expected a size such as \"64GB\"") from None
    walltime = opts.pop("walltime", None)
    if walltime is not None and not re.fullmatch(r"(\d+-)?\d+(:\d\d){0,2}", str(walltime)):
        raise ConfigError(f"[batch] walltime {walltime!r}: expected \"HH:MM:SS\" (or "
                          "\"D-HH:MM:SS\", \"MM\")")
    processes = _positive_int(opts.pop("processes", None), "[batch] processes")
    if processes is None:
        processes = max(1, cores // (threads_per_worker or 1))
    threads = threads_per_worker or max(1, cores // processes)
    if processes * threads > cores:
        raise ConfigError(f"[batch] processes = {processes} × threads_per_worker = {threads} "
                          f"needs {processes * threads} CPUs but a job has cores = {cores}")
    jobs = _positive_int(opts.pop("jobs", None), "[batch] jobs")
    if jobs is None:
        jobs = math.ceil(n_workers / processes) if n_workers else 1
    prologue = [f"export {k}={v}" for k, v in thread_env(threads).items()]
    prologue += list(opts.pop("job_script_prologue", []))
    kwargs: dict[str, Any] = {
        # one dask thread per worker process (one pair at a time); SLURM books all the cores
        "cores": processes, "processes": processes, "job_cpu": cores, "memory": memory,
        "job_script_prologue": prologue}
    if walltime is not None:
        kwargs["walltime"] = str(walltime)
    kwargs.update(opts)
    return kwargs, jobs


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    """Ignore SIGINT while worker processes are spawned, so that they inherit the ignore.

    A Ctrl-C (sent to the whole process group) then reaches only this process, which stops the
    batch cleanly and closes the workers, instead of every worker dying with a traceback.
    """
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


@contextlib.contextmanager
def _scoped_environ(updates: Mapping[str, str], restore: Sequence[str] = ()) -> Iterator[None]:
    """Set ``updates`` in ``os.environ``; on exit restore them and the keys ``restore``."""
    keys = set(updates) | set(restore)
    saved = {k: os.environ.get(k) for k in keys}
    os.environ.update(updates)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _quick_exit_plugin():
    """A worker plugin that freezes the garbage collector when its worker closes.

    A worker that compiled the numba kernels holds millions of objects; the interpreter's
    last garbage collection at exit then outlasts the nanny's 4 s grace and the worker is
    killed with a warning ("Worker process still alive after 4.0 seconds, killing").
    Frozen objects are skipped by that collection: the worker exits in well under a second.
    """
    from distributed import WorkerPlugin

    class QuickExit(WorkerPlugin):
        name = "plenopiv-quick-exit"

        def teardown(self, worker):
            import gc

            gc.freeze()

    return QuickExit()


@contextlib.contextmanager
def _open_client(kind: str, cluster: str, n_workers: int | None, threads: int | None,
                 retries: int, options: dict) -> Iterator[Any]:
    """Yield a connected ``Client``; clusters started here are closed on exit, always."""
    import dask
    from distributed import Client

    # The scheduler reads these when it starts (local and SLURM: in this process). A task whose
    # worker dies is given to another worker up to `retries` times; one task at a time per
    # worker, so that a crashing pair does not count against another pair queued beside it.
    sched_cfg = {"distributed.scheduler.allowed-failures": retries,
                 "distributed.scheduler.worker-saturation": 1.0}
    if kind == "address":
        try:
            client = Client(cluster, timeout="20s", set_as_default=False)
        except (OSError, TimeoutError) as exc:
            raise ConfigError(f"cannot reach the dask scheduler at {cluster!r}: {exc}") from None
        try:
            yield client
        finally:
            client.close()
        return

    env = thread_env(threads)
    spawn_keys = list(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
    # BLAS/OpenMP read their variables when numpy loads: set them before the worker processes
    # are spawned (dask's pre-spawn environment prefers os.environ over its config). Not
    # NUMBA_NUM_THREADS: numba in this process would refuse a changed value once its threads
    # run; the Nanny's `env` sets it in each worker before the worker imports anything.
    blas = {k: v for k, v in env.items() if k != "NUMBA_NUM_THREADS"}
    with contextlib.ExitStack() as stack:
        # ... and leave this process's environment as it was (dask also sets its own keys)
        stack.enter_context(_scoped_environ(blas, restore=[*spawn_keys, "PYTHONHASHSEED",
                                                           "__DASK_PARENT_PID"]))
        stack.enter_context(dask.config.set(sched_cfg))
        if kind == "local":
            from distributed import LocalCluster

            kw = {"dashboard_address": ":0", **options}  # a free port: no clash with another batch
            with _sigint_ignored():
                cl = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                  env=env, **kw)
        else:
            cl = _slurm_cluster(options, threads, n_workers)
        stack.callback(cl.close)
        client = Client(cl, set_as_default=False)
        stack.callback(client.close)
        register = getattr(client, "register_plugin", None) or client.register_worker_plugin
        register(_quick_exit_plugin())
        yield client


def _import_jobqueue():
    try:
        import dask_jobqueue
    except ImportError:
        raise ConfigError("cluster='slurm' needs dask-jobqueue, which is not installed: "
                          "pip install 'plenopiv[hpc]'") from None
    return dask_jobqueue


def _slurm_cluster(options: dict, threads: int | None, n_workers: int | None):
    dask_jobqueue = _import_jobqueue()
    kwargs, jobs = slurm_cluster_kwargs(options, threads_per_worker=threads,
                                        n_workers=n_workers)
    cl = dask_jobqueue.SLURMCluster(**kwargs)
    try:
        cl.scale(jobs=jobs)
    except BaseException:
        cl.close()
        raise
    return cl


def batch_options(batch: Mapping) -> dict:
    """Keywords of :func:`run_batch` from an experiment's ``[batch]`` table.

    ``cluster``, ``workers`` (→ ``n_workers``), ``threads_per_worker`` and ``retries`` are
    options of :func:`run_batch`; ``queue``, ``account``, ``cores``, ``processes``, ``memory``,
    ``walltime``, ``jobs`` and the other SLURM keys go to ``cluster_options`` (used only with
    ``cluster = "slurm"``). Keys that are None are left out.
    """
    b = {k: v for k, v in dict(batch).items() if v is not None}
    out: dict[str, Any] = {}
    for key, arg in (("cluster", "cluster"), ("workers", "n_workers"),
                     ("threads_per_worker", "threads_per_worker"), ("retries", "retries")):
        if key in b:
            out[arg] = b.pop(key)
    unknown = sorted(set(b) - set(_SLURM_OPTIONS))
    if unknown:
        raise ConfigError(f"[batch] unknown key {unknown[0]!r}; expected some of cluster, "
                          f"workers, threads_per_worker, retries, {', '.join(_SLURM_OPTIONS)}")
    if out.get("cluster", "local") == "slurm":
        out["cluster_options"] = b
    return out
