"""Many image pairs on dask: a local process pool, a SLURM allocation or an existing scheduler.

A batch is a list of :class:`PairJob` (two images in, one HDF5 product out) and a ``process``
function that turns one job into its product. :func:`run_batch` sends the jobs to dask worker
processes, shows a progress bar, records every failure with its reason and goes on with the
rest, and writes ``batch_summary.json`` beside the products. It is resumable: a job whose
product is already complete is skipped without being sent anywhere.

This is the only module that imports dask (STYLE.md rule 1); it does so inside the functions
that need it, so that ``import plenopiv.batch`` stays cheap.

The completeness contract of ``process``
----------------------------------------
``process(job) -> dict`` is a picklable, top-level function (dask sends it by reference to
worker processes, so it must be importable there). It

1. reads ``job.image_a`` and ``job.image_b`` (e.g. with
   :func:`plenopiv.products.images.read_image`);
2. writes ``job.output`` **atomically** (:func:`plenopiv.products.hdf5.write_h5` or
   :func:`plenopiv.products.files.atomic_path`), so that a half-written file never exists
   under the final name: a killed run leaves at most a hidden ``.NAME.XXXX.part``
   temporary, which the next :func:`run_batch` deletes;
3. marks the product complete as its **last** write: ``mark_complete(job.output)`` after the
   file is written, or ``mark_complete(tmp)`` inside an ``atomic_path`` block, or
   ``write_h5(job.output, ..., attrs={"complete": True})`` when one atomic write holds
   everything. The mark is the root attribute ``complete = True`` (:data:`COMPLETE_ATTR`);
4. returns a small JSON-friendly dict (numbers, strings, short lists): it travels back to the
   client and into ``batch_summary.json``. ``None`` counts as ``{}``.

A product is complete when :func:`is_complete` says so: it opens as HDF5 and its root
attribute ``complete`` is true. Only complete products are skipped on resume; a product
without the mark (a process that died between its writes, or a file from elsewhere) is
recomputed and replaced.

Resume is keyed on what made each product. A job may carry an ``identity``: a mapping of
content hashes (``plenopiv run``: the experiment's settings, the calibration file, the two
images). ``process`` stores it in the product (root attribute ``identity``, JSON;
``mark_complete(path, identity=job.identity)`` does both). A complete product whose stored
identity differs from the job's (other settings, another calibration, other images, or
another pair's product copied over the name) is recomputed, and the summary lists it under
``recomputed`` with what changed.

When ``process`` returns but its product is not complete (or does not record the job's
identity), the job is recorded as failed (a resume would otherwise redo it forever).

An exception raised by ``process`` is deterministic for a given input (a corrupt image, a bad
config): it is caught on the worker, recorded (type, message, traceback) and NOT retried. A
worker process that dies while running a job (segfault, ``os._exit``, killed for memory) is a
different matter: dask gives the job to another worker, up to ``retries`` more times, then
records it as failed (``KilledWorker``). Dask counts a death against every job assigned to
the dead worker, the one it was running and any waiting behind it; so that an innocent pair
is not charged, no more pairs are submitted than the cluster has worker slots. A pair that
dask re-assigns after a death, while the other workers are busy or restarting, can still
wait behind a crashing one and share its count: give ``retries`` ≥ 2 where pairs crash.
"""

from __future__ import annotations

import contextlib
import glob
import json
import math
import os
import re
import sys
import time
import traceback as tb
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from plenopiv.errors import EXIT_INTERRUPTED, ConfigError, PlenopivError
from plenopiv.products.files import atomic_path
from plenopiv.products.jsonio import finite_json, to_json

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
    "product_identity",
    "run_batch",
    "slurm_cluster_kwargs",
    "thread_env",
]

#: Root attribute of a product that marks it complete (the last thing ``process`` writes).
COMPLETE_ATTR = "complete"
#: Root attribute of a product holding the identity (JSON) of the settings and inputs it was
#: made from.
IDENTITY_ATTR = "identity"
#: File name of the batch summary written in the output folder.
SUMMARY_NAME = "batch_summary.json"
#: Environment variables that set the thread pools of numba and the BLAS/OpenMP libraries.
THREAD_ENV_VARS = ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS",
                   "OPENBLAS_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")

_H5_SUFFIXES = (".h5", ".hdf5")
_CLUSTER_KINDS = ("local", "slurm")
_ADDRESS = re.compile(r"^(?:(?:tcp|tls|inproc|ucx|ws|wss)://\S+|[\w.\-]+:\d+)$")
_LOCAL_OPTIONS = ("memory_limit", "dashboard_address", "local_directory")
_SLURM_OPTIONS = ("queue", "account", "cores", "processes", "memory", "walltime", "jobs",
                  "job_extra_directives", "job_script_prologue", "local_directory",
                  "log_directory", "interface", "python")
_SEPARATORS = "_-. "


class BatchError(PlenopivError):
    """A batch job broke the contract of :func:`run_batch` (e.g. its product is not complete)."""


class BatchInterrupted(PlenopivError):
    """The batch was stopped by Ctrl-C; its summary was written and a rerun resumes it.

    ``summary`` holds :meth:`BatchSummary.to_dict` of the pairs finished before the stop.
    """

    exit_status = EXIT_INTERRUPTED

    def __init__(self, message: str, summary: dict):
        super().__init__(message)
        self.summary = summary


# ---- jobs ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class PairJob:
    """One image pair and the product it becomes.

    Parameters
    ----------
    name : str
        Unique name of the pair in its batch (the progress, the summary and the dask key use
        it); no path separators.
    image_a, image_b : str
        The first and second exposure: an image file (TIFF, PNG) or ``file.h5:/dataset``.
    output : Path
        The product of this pair, an HDF5 file (``.h5``/``.hdf5``).
    identity : mapping of str to str, optional
        What makes this pair's product (e.g. hashes of the settings, the calibration and the
        two images); stored in the product by ``process``, compared on resume.
    """

    name: str
    image_a: str
    image_b: str
    output: Path
    identity: Mapping[str, str] | None = field(default=None, compare=False)

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name.strip() or "/" in self.name \
                or os.sep in self.name:
            raise ConfigError(f"pair name {self.name!r}: expected a non-empty string without "
                              "path separators")
        object.__setattr__(self, "image_a", str(self.image_a))
        object.__setattr__(self, "image_b", str(self.image_b))
        out = Path(self.output)
        if out.suffix.lower() not in _H5_SUFFIXES:
            raise ConfigError(f"pair {self.name!r}: output {str(out)!r} must be an HDF5 file "
                              "ending in .h5 or .hdf5 (its completeness is an HDF5 attribute)")
        object.__setattr__(self, "output", out)

    def to_dict(self) -> dict:
        """Return the job as JSON-friendly values."""
        return {"name": self.name, "image_a": self.image_a, "image_b": self.image_b,
                "output": str(self.output),
                "identity": None if self.identity is None else dict(self.identity)}


def _natural_key(s: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s)]


def _glob_regex(pattern: str) -> re.Pattern:
    """Build a regex matching what ``glob`` matches for ``pattern``, capturing wildcards."""
    out, i, n = [], 0, len(pattern)
    while i < n:
        c = pattern[i]
        if pattern.startswith("**/", i):
            out.append("((?:.*/)?)")
            i += 3
        elif pattern.startswith("**", i):
            out.append("(.*)")
            i += 2
        elif c == "*":
            out.append("([^/]*)")
            i += 1
        elif c == "?":
            out.append("([^/])")
            i += 1
        elif c == "[":
            j = i + 1
            if j < n and pattern[j] == "!":
                j += 1
            if j < n and pattern[j] == "]":
                j += 1
            j = pattern.find("]", j)
            if j < 0:
                out.append(re.escape(c))
                i += 1
                continue
            body = pattern[i + 1:j]
            if body.startswith("!"):
                body = "^" + body[1:]
            out.append("([" + body.replace("\\", "\\\\") + "])")
            i = j + 1
        else:
            out.append(re.escape(c))
            i += 1
    return re.compile("".join(out) + r"\Z")


def _matches(pattern: str, root: Path, what: str) -> list[tuple[str, Path]]:
    """Return ``[(key, absolute path)]`` of the files matching ``pattern``, sorted."""
    pattern = str(pattern)
    found = [p for p in glob.glob(pattern, root_dir=root, recursive=True)
             if (root / p).is_file()]
    if not found:
        raise ConfigError(f"{what} {pattern!r} matches no file (looked in {str(root)!r})")
    rx = _glob_regex(pattern)
    out = []
    for p in found:
        m = rx.match(p)
        key = "\x00".join(m.groups()) if m else Path(p).stem
        out.append((key, (root / p).resolve()))
    out.sort(key=lambda kp: _natural_key(str(kp[1])))
    return out


def _pair_name(a: Path, b: Path) -> str:
    prefix = os.path.commonprefix([a.stem, b.stem]).rstrip(_SEPARATORS)
    return prefix


def discover_pairs(pattern_a: str, pattern_b: str | None = None, *, out_dir: str | Path,
                   pair_by: str = "auto", root: str | Path | None = None,
                   output_name: str = "{name}.h5",
                   datasets: tuple[str, str] = ("/image_a", "/image_b")) -> list[PairJob]:
    """Build the jobs of a batch from glob patterns.

    Two patterns (``images/*_A.tif``, ``images/*_B.tif``) pair the files of the first with
    those of the second; one pattern of HDF5 files (``pairs/*.h5``) makes one job per file,
    its exposures read from the datasets ``datasets`` (``/image_a`` and ``/image_b``).

    Parameters
    ----------
    pattern_a, pattern_b : str
        Glob patterns (``**`` recurses), relative to ``root``. Hidden files are not matched.
    out_dir : str or Path
        Folder of the products, relative to ``root``.
    pair_by : {"auto", "stem", "order"}
        ``"stem"``: files pair when the parts matched by the wildcards agree
        (``run_07_A.tif`` with ``run_07_B.tif``); a file without partner is an error.
        ``"order"``: the i-th file of each pattern in natural sort order (``frame_2`` before
        ``frame_10``). ``"auto"`` (default): by stem when the two patterns' wildcard parts
        agree, in order when they share none at all (``A_0001.tif`` / ``B_0001.tif`` under
        ``A/*.tif`` / ``B/*.tif``), and an error when they agree only in part (files missing).
    root : str or Path, optional
        Folder the patterns and ``out_dir`` are relative to (default: the current folder);
        e.g. the experiment file's folder.
    output_name : str
        File name of each product; ``{name}`` is the pair's name (the common start of the two
        file stems, ``run_07`` above; the first file's stem when that is empty or not unique).
    datasets : (str, str)
        The exposures' datasets in one-file-per-pair mode.

    Returns
    -------
    list of PairJob
        In natural sort order of the first exposure, with absolute paths.

    Raises
    ------
    ConfigError
        When a pattern matches nothing, the counts differ, a file has no partner, two pairs get
        the same name, or a product would overwrite an input.
    """
    if pair_by not in ("auto", "stem", "order"):
        raise ConfigError(f"pair_by {pair_by!r}: expected one of 'auto', 'stem', 'order'")
    if "{name}" not in output_name or not output_name.lower().endswith(_H5_SUFFIXES):
        raise ConfigError(f"output_name {output_name!r}: expected a file name containing "
                          "'{name}' and ending in .h5")
    base = Path.cwd() if root is None else Path(root)
    if not base.is_dir():
        raise ConfigError(f"root {str(base)!r} is not a folder")
    out = (base / out_dir).resolve()
    a = _matches(pattern_a, base, "pattern_a")
    if pattern_b is None:
        not_h5 = [str(p) for _, p in a if p.suffix.lower() not in _H5_SUFFIXES]
        if not_h5:
            raise ConfigError(f"pattern_a {pattern_a!r} without pattern_b expects one HDF5 file "
                              f"per pair holding {datasets[0]} and {datasets[1]}, but it "
                              f"matches {len(not_h5)} other files (first: {not_h5[0]!r}); "
                              "give the second exposures' pattern as pattern_b")
        triples = [(p.stem, f"{p}:{datasets[0]}", f"{p}:{datasets[1]}") for _, p in a]
        inputs = {p for _, p in a}
    else:
        b = _matches(pattern_b, base, "pattern_b")
        both = {p for _, p in a} & {p for _, p in b}
        if both:
            raise ConfigError(f"pattern_a {pattern_a!r} and pattern_b {pattern_b!r} both match "
                              f"{len(both)} files (first: {str(sorted(both)[0])!r}): each "
                              "exposure must match only one pattern")
        pairs = _pair_files(a, b, pattern_a, pattern_b, pair_by)
        names = [_pair_name(pa, pb) for pa, pb in pairs]
        if any(not n for n in names) or len(set(names)) != len(names):
            names = [pa.stem for pa, _ in pairs]
        triples = [(n, str(pa), str(pb)) for n, (pa, pb) in zip(names, pairs, strict=True)]
        inputs = {p for _, p in a} | {p for _, p in b}
    seen: dict[str, str] = {}
    for name, ia, _ in triples:
        if name in seen:
            raise ConfigError(f"two pairs get the name {name!r} ({seen[name]!r} and {ia!r}); "
                              "rename the files or use patterns that tell them apart")
        seen[name] = ia
    jobs = [PairJob(n, ia, ib, out / output_name.format(name=n)) for n, ia, ib in triples]
    clash = [j for j in jobs if j.output.resolve() in inputs]
    if clash:
        raise ConfigError(f"the product {str(clash[0].output)!r} of pair {clash[0].name!r} "
                          "would overwrite an input image; choose another out_dir or "
                          "output_name")
    return jobs


def _pair_files(a, b, pattern_a, pattern_b, pair_by) -> list[tuple[Path, Path]]:
    keys_a = {k: p for k, p in a}
    keys_b = {k: p for k, p in b}
    unique = len(keys_a) == len(a) and len(keys_b) == len(b)
    common = keys_a.keys() & keys_b.keys()
    if pair_by == "auto":
        if unique and common and len(common) == len(a) == len(b):
            pair_by = "stem"
        elif not common:
            pair_by = "order"
        else:
            pair_by = "stem"  # partial agreement: report the files without partner
    if pair_by == "order":
        if len(a) != len(b):
            raise ConfigError(f"pattern_a {pattern_a!r} matches {len(a)} files but pattern_b "
                              f"{pattern_b!r} matches {len(b)}: expected as many second as "
                              "first exposures")
        return [(pa, pb) for (_, pa), (_, pb) in zip(a, b, strict=True)]
    if not unique:
        raise ConfigError(f"pair_by='stem': the wildcards of {pattern_a!r} / {pattern_b!r} do "
                          "not tell the files apart; use pair_by='order' ([images] pair_by = "
                          "\"order\" in an experiment file)")
    only_a = [str(keys_a[k]) for k in keys_a.keys() - common]
    only_b = [str(keys_b[k]) for k in keys_b.keys() - common]
    if only_a or only_b:
        parts = []
        if only_a:
            parts.append(f"{len(only_a)} first exposures have no second "
                         f"(e.g. {sorted(only_a)[:3]})")
        if only_b:
            parts.append(f"{len(only_b)} second exposures have no first "
                         f"(e.g. {sorted(only_b)[:3]})")
        raise ConfigError(f"pattern_a {pattern_a!r} ({len(a)} files) and pattern_b "
                          f"{pattern_b!r} ({len(b)} files) do not pair by their wildcard "
                          f"parts: {'; '.join(parts)}. Add the missing files, or use "
                          "pair_by='order' ([images] pair_by = \"order\" in an experiment "
                          "file) to pair them in sorted order")
    return [(p, keys_b[k]) for k, p in a]


# ---- completeness --------------------------------------------------------------------------


def mark_complete(path: str | Path, identity: Mapping[str, str] | None = None) -> None:
    """Mark the HDF5 product ``path`` complete: the root attribute ``complete = True``
    (and ``identity``, the job's, when given).

    Call it as the last write of a product, after the file has been written and closed (or on
    the temporary path inside an :func:`plenopiv.products.files.atomic_path` block). See the module
    docstring for the contract.
    """
    import h5py

    with h5py.File(path, "r+") as fh:
        if identity is not None:
            fh.attrs[IDENTITY_ATTR] = json.dumps(dict(identity), sort_keys=True)
        fh.flush()
        fh.attrs[COMPLETE_ATTR] = True


def product_identity(path: str | Path) -> dict | None:
    """The identity stored in a product (None when it has none or cannot be read)."""
    import h5py

    try:
        with h5py.File(path, "r") as fh:
            raw = fh.attrs.get(IDENTITY_ATTR)
    except Exception:  # noqa: BLE001 - unreadable: no identity
        return None
    if raw is None:
        return None
    try:
        out = json.loads(raw)
    except (TypeError, ValueError):
        return None
    return out if isinstance(out, dict) else None


_IDENTITY_WORDS = {"settings": "the settings", "calibration": "the calibration",
                   "image_a": "the first image", "image_b": "the second image"}


def _stale_reason(job: PairJob) -> str | None:
    """Why a complete product must be recomputed for ``job`` (None: it may be kept)."""
    if job.identity is None:
        return None
    stored = product_identity(job.output)
    if stored is None:
        return ("the product records no identity of its settings and inputs (made by an "
                "older plenopiv or elsewhere)")
    want = dict(job.identity)
    changed = [k for k in sorted(set(want) | set(stored)) if want.get(k) != stored.get(k)]
    if not changed:
        return None
    return "made with other " + ", ".join(_IDENTITY_WORDS.get(k, k).replace("the ", "", 1)
                                          for k in changed)


def is_complete(path: str | Path) -> bool:
    """Whether ``path`` is a complete product: an HDF5 file whose root ``complete`` is true.

    A missing, unreadable or truncated file, or one without the mark, is not complete.
    """
    import h5py

    p = Path(path)
    if not p.is_file():
        return False
    try:
        with h5py.File(p, "r") as fh:
            return bool(fh.attrs.get(COMPLETE_ATTR, False))
    except Exception:  # noqa: BLE001 - any failure to read the file means "not complete"
        return False


def _remove_stale_parts(jobs: Sequence[PairJob]) -> list[Path]:
    """Delete the temporaries that a killed run left beside the jobs' products.

    :func:`plenopiv.products.files.atomic_path` names them ``.{final name}.XXXXXXXX.part`` (and a
    writer that appends a suffix, ``.part.vti``). Caught: those of the product itself, of its
    side products (``.{stem}.png...``) and of every file named after the pair
    (``.{name}_volume_A.h5...``, ``.{name}_vectors.vti...``).
    """
    removed = []
    for job in jobs:
        folder = job.output.parent
        if not folder.is_dir():
            continue
        prefixes = {glob.escape(job.output.stem), glob.escape(job.name)}
        patterns = [f".{pre}{sep}*.part{tail}" for pre in prefixes for sep in (".", "_")
                    for tail in ("", ".*")]
        for pattern in patterns:
            for p in folder.glob(pattern):
                with contextlib.suppress(FileNotFoundError):
                    p.unlink()
                    removed.append(p)
    return removed


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
        d = {"n_jobs": self.n_jobs, "n_done": len(self.done),
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
        return finite_json(json.loads(json.dumps(d, default=_json_default)))


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


# ---- clusters ------------------------------------------------------------------------------


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
    """Ignore SIGINT while worker processes are spawned, so that they inherit the ignore: a
    Ctrl-C (sent to the whole process group) then reaches only this process, which stops the
    batch cleanly and closes the workers, instead of every worker dying with a traceback."""
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
                        cluster_options: Mapping | None = None) -> None:
    """Check the cluster options of :func:`run_batch` without starting anything (so that a
    command can refuse them before its own long preparations)."""
    kind = _cluster_kind(cluster)
    _positive_int(n_workers, "n_workers")
    _positive_int(threads_per_worker, "threads_per_worker")
    _positive_int(retries, "retries", allow_none=False, minimum=0)
    allowed = {"local": _LOCAL_OPTIONS, "slurm": _SLURM_OPTIONS}.get(kind, ())
    _check_options(cluster_options, allowed, kind)


def run_batch(jobs: Sequence[PairJob], process: Callable[[PairJob], dict], *,
              cluster: str = "local", n_workers: int | None = None,
              threads_per_worker: int | None = None, resume: bool = True, retries: int = 2,
              progress: bool = True, cluster_options: Mapping | None = None,
              summary_path: str | Path | None = None) -> BatchSummary:
    """Run ``process`` on every job on dask worker processes; resumable and fault tolerant.

    Parameters
    ----------
    jobs : sequence of PairJob
        Unique names, unique outputs (see :func:`discover_pairs`).
    process : callable
        ``process(job) -> dict``, a picklable top-level function that writes ``job.output``
        atomically and marks it complete (the contract is in the module docstring).
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
        Skip jobs whose product :func:`is_complete` (default True). ``False`` recomputes all.
        Only the mark is checked, not whether the inputs or the config changed since. Either
        way, the ``.part`` temporaries beside the products are deleted first: run one batch
        per output folder at a time.
    retries : int
        How many more times a job is run after the worker process running it died (default
        2). Exceptions raised by ``process`` are deterministic and are not retried. With a
        scheduler address the scheduler's own ``allowed-failures`` applies instead.
    progress : bool
        Show a progress bar (and one line per failure) on stderr.
    cluster_options : mapping, optional
        Local: ``memory_limit``, ``dashboard_address`` (default ":0", a free port),
        ``local_directory``. SLURM: see :func:`slurm_cluster_kwargs` (the ``[batch]`` table;
        :func:`batch_options` maps it).
    summary_path : str or Path, optional
        Where to write the JSON summary (default: ``batch_summary.json`` in the products'
        common folder). Written atomically, failures included.

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
    """
    jobs = _check_jobs(jobs)
    _check_process(process)
    kind = _cluster_kind(cluster)
    slots = None                      # pairs run at once, when known before the cluster starts
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
    summary_file = Path(summary_path) if summary_path is not None else \
        _default_summary_path(jobs)

    t0 = time.perf_counter()
    removed = _remove_stale_parts(jobs)
    for p in summary_file.parent.glob(f".{glob.escape(summary_file.name)}.*.part"):
        with contextlib.suppress(FileNotFoundError):
            p.unlink()
            removed.append(p)
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
        todo.append(job)
    interrupted = False
    try:
        if todo:
            with _open_client(kind, cluster, n_workers, threads, retries, options) as client:
                _submit_and_collect(client, todo, process, results,
                                    threads=threads if kind != "address" else None,
                                    slots=slots, retries=retries, progress=progress,
                                    total=len(jobs), skipped=len(jobs) - len(todo),
                                    known_retries=kind != "address")
    except KeyboardInterrupt:
        interrupted = True
    for job in jobs:
        if job.name not in results:
            results[job.name] = JobResult(job.name, "interrupted", str(job.output))
    if interrupted:          # a write killed part way leaves a temporary: remove it now
        removed += _remove_stale_parts(jobs)
    ordered = tuple(results[j.name] for j in jobs)
    summary = BatchSummary(
        done=tuple(r.name for r in ordered if r.status == "done"),
        skipped=tuple(r.name for r in ordered if r.status == "skipped"),
        failed=tuple((r.name, f"{r.error_type}: {r.error}") for r in ordered
                     if r.status == "failed"),
        seconds=time.perf_counter() - t0, results=ordered, cluster=cluster,
        n_workers=n_workers, threads_per_worker=threads,
        removed_parts=tuple(str(p) for p in removed), summary_path=str(summary_file),
        recomputed=tuple(recomputed),
        interrupted=tuple(r.name for r in ordered if r.status == "interrupted"))
    with atomic_path(summary_file) as tmp:
        tmp.write_text(json.dumps(summary.to_dict(tracebacks=True), indent=1,
                                  allow_nan=False) + "\n")
    if interrupted:
        raise BatchInterrupted(
            f"interrupted (Ctrl-C) after {len(summary.done)} of {summary.n_jobs} pairs "
            f"({len(summary.interrupted)} not finished, {len(summary.failed)} failed); "
            f"summary written to {summary_file}; run the same command again to resume",
            summary.to_dict())
    return summary


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
    """Run ``todo`` on the cluster, filling ``results`` as pairs finish (so that a Ctrl-C
    leaves the finished ones in it)."""
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
