"""The dask side of :mod:`plenopiv.batch`: cluster options, clients, worker thread pools.

A ``"local"`` cluster of worker processes, a SLURM cluster (dask-jobqueue), or the address
of a running scheduler; each worker's numba/BLAS/OpenMP threads pinned to
``threads_per_worker``. dask is imported inside the functions that need it.
"""

from __future__ import annotations

import contextlib
import logging
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


def worker_allocator_env(environ=None) -> dict[str, str]:
    """The allocator variables a batch's worker processes start with: one malloc arena.

    A worker runs its pairs in a thread of its own, and glibc serves such a thread from an
    arena of 64 MB heaps, so every larger array (an image's rays, a volume) is mapped afresh
    and handed back when freed, whatever :func:`plenopiv.resources.reuse_freed_memory` sets.
    With one arena they come from the process's heap, where that setting keeps them for
    reuse. Only read when the process starts, so it is set before the workers are spawned.
    Empty where the user set an allocator variable (``environ``: the command's own
    environment by default), which is then theirs to choose.
    """
    from plenopiv.resources import allocator_environment

    environ = os.environ if environ is None else environ
    if allocator_environment(environ) or "MALLOC_ARENA_MAX" in environ:
        return {}
    return {"MALLOC_ARENA_MAX": "1"}


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


#: Default seconds to wait for a scheduler address to answer (``[batch] connect_timeout_s``).
CONNECT_TIMEOUT_S = 10.0
#: What a dask server says first on a connection: a frame holding its handshake.
_HANDSHAKE_KEY = b"pickle-protocol"
_MAX_HANDSHAKE_BYTES = 1 << 16


def _host_port(address: str) -> tuple[str, str, int] | None:
    """``(scheme, host, port)`` of a scheduler address; None where it is not TCP-like."""
    scheme, sep, rest = address.partition("://")
    if not sep:
        scheme, rest = "tcp", address
    if scheme not in ("tcp", "tls"):
        return None
    host, _, port = rest.rstrip("/").rpartition(":")
    try:
        return scheme, host.strip("[]"), int(port)
    except ValueError:
        return None


def _read_some(sock, n: int, deadline: float) -> bytes:
    """Up to ``n`` bytes from ``sock`` before ``deadline`` (time.monotonic); fewer on EOF."""
    import socket
    import time

    data = b""
    while len(data) < n:
        left = deadline - time.monotonic()
        if left <= 0:
            break
        sock.settimeout(left)
        try:
            chunk = sock.recv(n - len(data))
        except (TimeoutError, socket.timeout, OSError):   # no answer in time, or a reset
            break
        if not chunk:
            break
        data += chunk
    return data


def _what_answered(sock, first: bytes, timeout: float) -> str | None:
    """Why the bytes a server sent first (``first``) are not a dask handshake; None if they are.

    A server that says nothing is asked ``GET /`` to tell an HTTP server (a dashboard).
    """
    import struct
    import time

    if not first:
        try:
            sock.sendall(b"GET / HTTP/1.0\r\nHost: plenopiv\r\n\r\n")
        except OSError:
            return "it accepted the connection and closed it without a word"
        reply = _read_some(sock, 64, time.monotonic() + min(timeout, 2.0))
        if reply.startswith(b"HTTP/"):
            return ("an HTTP server answered, not a dask scheduler (a dashboard? dask's "
                    "scheduler listens on 8786 by default, its dashboard on 8787)")
        return (f"it accepted the connection but sent no dask handshake within {timeout:g} s "
                "(or closed it): not a dask scheduler")
    if first.startswith(b"HTTP/"):
        return "an HTTP server answered, not a dask scheduler"
    (n,) = struct.unpack("<Q", first[:8].ljust(8, b"\0"))
    body = b""
    if len(first) == 8 and 0 < n <= _MAX_HANDSHAKE_BYTES:
        body = _read_some(sock, n, time.monotonic() + timeout)
    if _HANDSHAKE_KEY in body:
        return None
    return f"something answered that is not a dask scheduler (its first bytes: {first[:8]!r})"


def probe_scheduler(address: str, timeout: float = CONNECT_TIMEOUT_S) -> None:
    """Check that a dask scheduler answers at ``address`` within ``timeout`` seconds.

    Raises
    ------
    ConfigError
        Saying what answered: nothing (an unknown host, a refused connection, no answer in
        time) or something that is not a dask scheduler (an HTTP server, other bytes). TLS
        addresses are checked up to the connection; other protocols are left to dask.
    """
    import socket
    import time

    parts = _host_port(address)
    if parts is None:
        return
    scheme, host, port = parts
    where = f"the dask scheduler address {address!r}"
    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except socket.gaierror as exc:
        raise ConfigError(f"{where}: host {host!r} is not known ({exc.strerror})") from None
    except (TimeoutError, socket.timeout):
        raise ConfigError(f"{where}: nothing answered within {timeout:g} s (a host that is "
                          "down, unreachable, or a firewall; [batch] connect_timeout_s sets "
                          "the wait)") from None
    except ConnectionRefusedError:
        raise ConfigError(f"{where}: nothing listens on port {port} of {host} (connection "
                          "refused); is the scheduler running, on this port?") from None
    except OSError as exc:
        raise ConfigError(f"{where}: cannot connect ({exc.strerror or exc})") from None
    with sock:
        if scheme == "tls":
            return
        why = _what_answered(sock, _read_some(sock, 8, time.monotonic() + timeout), timeout)
    if why is not None:
        raise ConfigError(f"{where}: {why}")


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
    prologue = [f"export {k}={v}" for k, v in {**thread_env(threads),
                                               **worker_allocator_env()}.items()]
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
def _sigterm_deferred() -> Iterator[None]:
    """Hold a SIGTERM that arrives while a cluster starts until it can be closed.

    The signal is recorded and raised again on leaving, where the cluster and its client are
    registered for closing: a cluster stopped half way through its start leaves workers that
    nothing closes (and dask's exit handler fails on them with a traceback).
    """
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received = []
    old = signal.signal(signal.SIGTERM, lambda signum, frame: received.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)
        if received:
            signal.raise_signal(signal.SIGTERM)      # now handled as it would have been


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


class _HeartbeatOfAStoppedBatch:
    """A logging filter: a worker's failed heartbeat once its batch's scheduler is gone.

    The scheduler of a batch goes away only when the batch ends or is stopped (Ctrl-C,
    SIGTERM); a worker busy with a pair then logs the failed heartbeat with a traceback on
    the batch's stderr, after the batch's own one-line message.
    """

    def filter(self, record) -> bool:
        return not str(record.msg).startswith("Failed to communicate with scheduler during "
                                              "heartbeat")


def _quick_exit_plugin():
    """A worker plugin: quiet about the end of its batch, and quick to exit.

    It filters the failed heartbeat of a stopped batch (:class:`_HeartbeatOfAStoppedBatch`)
    and freezes the garbage collector when its worker closes: a worker that compiled the
    numba kernels holds millions of objects; the interpreter's last garbage collection at
    exit then outlasts the nanny's 4 s grace and the worker is killed with a warning
    ("Worker process still alive after 4.0 seconds, killing"). Frozen objects are skipped
    by that collection: the worker exits in well under a second.
    """
    from distributed import WorkerPlugin

    class QuickExit(WorkerPlugin):
        name = "plenopiv-quick-exit"

        def setup(self, worker):
            logging.getLogger("distributed.worker").addFilter(_HeartbeatOfAStoppedBatch())

        def teardown(self, worker):
            import gc

            gc.freeze()

    return QuickExit()


@contextlib.contextmanager
def _open_client(kind: str, cluster: str, n_workers: int | None, threads: int | None,
                 retries: int, options: dict, connect_timeout: float = CONNECT_TIMEOUT_S
                 ) -> Iterator[Any]:
    """Yield a connected ``Client``; clusters started here are closed on exit, always.

    A scheduler address is probed first (:func:`probe_scheduler`) and the connection bounded
    by ``connect_timeout`` seconds.
    """
    import dask
    from distributed import Client

    # The scheduler reads these when it starts (local and SLURM: in this process). A task whose
    # worker dies is given to another worker up to `retries` times; one task at a time per
    # worker, so that a crashing pair does not count against another pair queued beside it.
    sched_cfg = {"distributed.scheduler.allowed-failures": retries,
                 "distributed.scheduler.worker-saturation": 1.0}
    if kind == "address":
        probe_scheduler(cluster, connect_timeout)
        try:
            client = Client(cluster, timeout=f"{connect_timeout}s", set_as_default=False)
        except Exception as exc:  # noqa: BLE001 - whatever dask raises, one clear line
            raise ConfigError(f"the dask scheduler at {cluster!r} answered but the connection "
                              f"failed: {type(exc).__name__}: {exc}") from None
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
    allocator = worker_allocator_env()
    with contextlib.ExitStack() as stack:
        # ... and leave this process's environment as it was (dask also sets its own keys)
        stack.enter_context(_scoped_environ(blas, restore=[*spawn_keys, *allocator,
                                                           "PYTHONHASHSEED",
                                                           "__DASK_PARENT_PID"]))
        # the allocator's, before each worker process starts: its allocator reads them then
        spawn = {f"distributed.nanny.pre-spawn-environ.{k}": v for k, v in allocator.items()}
        stack.enter_context(dask.config.set({**sched_cfg, **spawn}))
        with _sigterm_deferred():      # a cluster half started could not be closed
            if kind == "local":
                from distributed import LocalCluster

                # a free port: no clash with another batch; the workers' log lines at ERROR
                # and above only (their warnings as a batch stops are not the user's concern)
                kw = {"dashboard_address": ":0", "silence_logs": logging.ERROR, **options}
                with _sigint_ignored():
                    cl = LocalCluster(n_workers=n_workers, threads_per_worker=1,
                                      processes=True, env=env, **kw)
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
    ``cluster = "slurm"``); ``connect_timeout_s`` becomes ``connect_timeout``. Keys that are
    None are left out.
    """
    b = {k: v for k, v in dict(batch).items() if v is not None}
    out: dict[str, Any] = {}
    for key, arg in (("cluster", "cluster"), ("workers", "n_workers"),
                     ("threads_per_worker", "threads_per_worker"), ("retries", "retries"),
                     ("connect_timeout_s", "connect_timeout")):
        if key in b:
            out[arg] = b.pop(key)
    unknown = sorted(set(b) - set(_SLURM_OPTIONS))
    if unknown:
        raise ConfigError(f"[batch] unknown key {unknown[0]!r}; expected some of cluster, "
                          "workers, threads_per_worker, retries, connect_timeout_s, "
                          f"{', '.join(_SLURM_OPTIONS)}")
    if out.get("cluster", "local") == "slurm":
        out["cluster_options"] = b
    return out
