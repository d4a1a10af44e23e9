"""plenopiv.batch on real dask clusters of worker processes, with tiny jobs.

The pairs are 16 × 16 TIFFs whose second exposure is the first plus a known offset
(10 counts × the pair's index), so each product's mean difference is known exactly.
The process functions are module level: dask sends them to the workers by reference.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import types
from pathlib import Path

import h5py
import numpy as np
import pytest

from plenopiv import batch
from plenopiv.batch import BatchSummary, run_batch
from plenopiv.batch.cluster import batch_options, slurm_cluster_kwargs
from plenopiv.batch.jobs import PairJob, discover_pairs, is_complete, mark_complete
from plenopiv.errors import ConfigError
from plenopiv.products.hdf5 import write_h5
from plenopiv.products.images import read_image, write_image

OFFSET = 10  # counts added to the second exposure per pair index


# ---- process functions (run on the workers) -------------------------------------------------


def mean_difference(job: PairJob) -> dict:
    """The contract: read both images, write the product atomically, mark it complete last."""
    import numba

    a = read_image(job.image_a).astype(np.float64)
    b = read_image(job.image_b).astype(np.float64)
    diff = float((b - a).mean())
    write_h5(job.output, {"/difference": b - a}, attrs={"mean_difference": diff},
             kind="test product")
    if "nomark" not in job.name:   # a process that breaks the contract
        mark_complete(job.output)
    return {"mean_difference": diff, "pid": os.getpid(),
            "numba_threads": numba.config.NUMBA_NUM_THREADS,
            "numba_get_num_threads": numba.get_num_threads(),
            "env": {k: os.environ.get(k) for k in batch.THREAD_ENV_VARS}}


def crashing(job: PairJob) -> dict:
    """Kill the worker process running ``die-once`` (first time only) and ``die-always``.

    A marker file beside the product counts the deaths (one pid per line).
    """
    marker = job.output.with_suffix(".deaths")
    if job.name.startswith("die-"):
        deaths = marker.read_text().split() if marker.exists() else []
        if job.name == "die-always" or not deaths:
            with open(marker, "a") as fh:
                fh.write(f"{os.getpid()}\n")
            os._exit(1)
    return mean_difference(job)


@dataclasses.dataclass(frozen=True)
class AllocatorProbe:
    """Set the worker's memory up as a pair's process does, with the allocator variables of
    the command, then count the page faults of nine 64 MB arrays allocated and freed."""

    allocator: tuple

    def __call__(self, job: PairJob) -> dict:
        import resource

        from plenopiv.resources import own_process_memory

        own_process_memory(self.allocator)
        np.ones(1 << 24, np.float32)
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for _ in range(9):
            a = np.ones(1 << 24, np.float32)
            del a
        faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
        write_h5(job.output, {"/faults": np.array([faults])}, kind="test product")
        mark_complete(job.output)
        return {"faults": faults, "trim": os.environ.get("MALLOC_TRIM_THRESHOLD_")}


# ---- helpers ---------------------------------------------------------------------------------


def make_pairs(folder: Path, n: int, rng, *, corrupt: int | None = None) -> list[Path]:
    """Write ``pair_II_A.tif`` / ``pair_II_B.tif`` (B = A + OFFSET·i); truncate A of ``corrupt``."""
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        a = rng.integers(100, 1000, size=(16, 16)).astype(np.uint16)
        write_image(folder / f"pair_{i:02d}_A.tif", a)
        write_image(folder / f"pair_{i:02d}_B.tif", a + np.uint16(OFFSET * i))
    if corrupt is not None:
        bad = folder / f"pair_{corrupt:02d}_A.tif"
        data = bad.read_bytes()
        bad.write_bytes(data[: len(data) * 2 // 5])    # a copy that stopped part way
        return [bad]
    return []


def parts(folder: Path) -> list[Path]:
    return sorted(folder.glob(".*.part"))


def index(name: str) -> int:
    return int(name.split("_")[1])


# ---- batches on a real LocalCluster ---------------------------------------------------------


def test_corrupt_image_fails_alone_and_workers_are_pinned(tmp_path, rng, monkeypatch, capsys):
    (bad,) = make_pairs(tmp_path / "images", 6, rng, corrupt=3)
    jobs = discover_pairs("images/*_A.tif", "images/*_B.tif", out_dir="out", root=tmp_path)
    # a user's environment asks for more threads; the workers must still get one each, and
    # this process's environment must come back as it was
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    monkeypatch.delenv("NUMBA_NUM_THREADS", raising=False)
    before = dict(os.environ)

    s = run_batch(jobs, mean_difference, n_workers=2, threads_per_worker=1, progress=True)

    assert dict(os.environ) == before
    assert isinstance(s, BatchSummary)
    assert s.done == ("pair_00", "pair_01", "pair_02", "pair_04", "pair_05")
    assert s.skipped == ()
    assert len(s.failed) == 1 and s.failed[0][0] == "pair_03"
    assert s.failed[0][1].startswith("ImageError: ") and str(bad) in s.failed[0][1]
    assert "corrupt or truncated" in s.failed[0][1]
    assert not s.ok and s.n_jobs == 6 and (s.n_workers, s.threads_per_worker) == (2, 1)
    failed = s.result("pair_03")
    assert failed.status == "failed" and failed.error_type == "ImageError"
    assert "read_image" in failed.traceback and failed.result is None
    assert not (tmp_path / "out" / "pair_03.h5").exists()
    for r in s.results:
        if r.status == "done":
            assert r.result["mean_difference"] == OFFSET * index(r.name)   # exact: integers
            assert is_complete(r.output)
            with h5py.File(r.output) as fh:
                assert fh.attrs["mean_difference"] == OFFSET * index(r.name)
            # one pair at a time per worker, one thread for numba and BLAS
            assert r.result["numba_threads"] == 1 and r.result["numba_get_num_threads"] == 1
            assert set(r.result["env"].values()) == {"1"}
            assert r.pid == r.result["pid"] and r.worker.startswith("tcp://")
            assert r.seconds >= 0 and r.start <= r.end
    assert len({r.pid for r in s.results if r.pid}) <= 2

    err = capsys.readouterr().err
    assert "plenopiv batch" not in err    # no bar: stderr is not a terminal here (a log)
    assert "failed pair_03: ImageError" in err            # the failure, as it happens
    on_disk = json.loads((tmp_path / "out" / batch.SUMMARY_NAME).read_text())
    assert on_disk["n_done"] == 5 and on_disk["n_failed"] == 1
    assert on_disk["failed"][0]["name"] == "pair_03"
    (rec,) = [r for r in on_disk["results"] if r["name"] == "pair_03"]
    assert "ImageError" in rec["traceback"]
    d = s.to_dict()
    json.dumps(d)
    assert d["n_failed"] == 1 and "traceback" not in d["results"][0]
    assert d["summary_path"] == str(tmp_path / "out" / batch.SUMMARY_NAME)


def test_resume_recomputes_only_missing_and_incomplete(tmp_path, rng, capsys):
    make_pairs(tmp_path / "images", 5, rng)
    out = tmp_path / "out"
    jobs = discover_pairs("images/*_A.tif", "images/*_B.tif", out_dir=out, root=tmp_path)
    first = run_batch(jobs, mean_difference, n_workers=2, progress=False)
    assert first.done == tuple(f"pair_{i:02d}" for i in range(5))
    assert "plenopiv batch" not in capsys.readouterr().err

    p = {j.name: j.output for j in jobs}
    p["pair_00"].unlink()                                   # lost
    p["pair_01"].unlink()                                   # killed before the rename ...
    (out / ".pair_01.h5.k1ll3d00.part").write_bytes(b"half an HDF5 file")  # ... left this
    write_h5(p["pair_02"], {"/difference": np.zeros(3)})    # killed before mark_complete
    (out / ".pair_03.h5.0ld0ld00.part").write_bytes(b"")    # stale temporary of a done pair
    old = 1_000_000_000
    for path in out.glob("*.h5"):
        os.utime(path, ns=(old, old))
    assert not is_complete(p["pair_02"]) and len(parts(out)) == 2

    second = run_batch(jobs, mean_difference, n_workers=2, progress=False)

    assert second.done == ("pair_00", "pair_01", "pair_02")
    assert second.skipped == ("pair_03", "pair_04") and second.failed == ()
    assert len(second.removed_parts) == 2 and parts(out) == []
    for name in ("pair_03", "pair_04"):                    # untouched
        assert p[name].stat().st_mtime_ns == old
    for name in second.done:                                # rewritten and complete
        assert is_complete(p[name]) and p[name].stat().st_mtime_ns > old
        assert second.result(name).result["mean_difference"] == OFFSET * index(name)
    assert second.result("pair_04").status == "skipped"

    # nothing left to do: no cluster is started (this address has no scheduler behind it)
    third = run_batch(jobs, mean_difference, cluster="tcp://127.0.0.1:9", progress=False)
    assert third.skipped == tuple(p) and third.done == () and third.failed == ()


def test_worker_death_is_retried_elsewhere_then_given_up(tmp_path, rng):
    make_pairs(tmp_path / "images", 4, rng)
    img = tmp_path / "images"
    out = tmp_path / "out"
    jobs = [PairJob(name, img / f"pair_{i:02d}_A.tif", img / f"pair_{i:02d}_B.tif",
                    out / f"{name}.h5")
            for i, name in enumerate(("pair_00", "die-once", "die-always", "pair_03"))]
    out.mkdir()

    # one worker: which pair a death is charged to is then certain (with two, dask may
    # re-assign die-once behind die-always while the other worker restarts; see batch.py)
    s = run_batch(jobs, crashing, n_workers=1, retries=1, progress=False)

    assert s.done == ("pair_00", "die-once", "pair_03")
    assert [n for n, _ in s.failed] == ["die-always"]
    lost = s.result("die-always")
    assert lost.error_type == "KilledWorker" and "died 2 times" in lost.error
    assert not (out / "die-always.h5").exists()
    # one death each for die-once, retries + 1 for die-always
    died = (out / "die-once.deaths").read_text().split()
    assert len(died) == 1 and str(s.result("die-once").pid) not in died
    assert len((out / "die-always.deaths").read_text().split()) == 2
    assert s.result("die-once").result["mean_difference"] == OFFSET * 1


def test_existing_scheduler_and_broken_contract(tmp_path, rng):
    from distributed import LocalCluster

    make_pairs(tmp_path / "images", 3, rng)
    img = tmp_path / "images"
    jobs = [PairJob(name, img / f"pair_{i:02d}_A.tif", img / f"pair_{i:02d}_B.tif",
                    tmp_path / "out" / f"{name}.h5")
            for i, name in enumerate(("pair_00", "pair_nomark", "pair_02"))]
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                      dashboard_address=":0") as cl:
        s = run_batch(jobs, mean_difference, cluster=cl.scheduler_address, progress=False)
        assert len(cl.scheduler.workers) == 1            # the user's cluster is left running
    assert s.done == ("pair_00", "pair_02")
    (name, error), = s.failed
    assert name == "pair_nomark" and error.startswith("BatchError: ")
    assert "mark_complete" in error
    assert s.cluster == cl.scheduler_address


class FakeSLURMCluster:
    """Stands in for dask_jobqueue.SLURMCluster: records its keywords, runs locally."""

    made: list[dict] = []

    def __init__(self, **kwargs):
        from distributed import LocalCluster

        FakeSLURMCluster.made.append(kwargs)
        self._local = LocalCluster(n_workers=0, threads_per_worker=1, processes=False,
                                   dashboard_address=":0")
        self.scheduler_address = self._local.scheduler_address
        self.jobs = None

    def scale(self, jobs=0):
        self.jobs = jobs
        self._local.scale(jobs * FakeSLURMCluster.made[-1]["processes"])

    def __getattr__(self, name):   # Client(cluster) asks for the scheduler, loop, ...
        return getattr(self._local, name)

    def close(self):
        self._local.close()


def test_slurm_runs_through_jobqueue(tmp_path, rng, monkeypatch):
    monkeypatch.setitem(sys.modules, "dask_jobqueue",
                        types.SimpleNamespace(SLURMCluster=FakeSLURMCluster))
    FakeSLURMCluster.made.clear()
    make_pairs(tmp_path / "images", 2, rng)
    jobs = discover_pairs("images/*_A.tif", "images/*_B.tif", out_dir="out", root=tmp_path)
    table = {"cluster": "slurm", "workers": None, "threads_per_worker": None, "retries": 1,
             "queue": "short", "cores": 2, "memory": "4GB", "walltime": "00:10:00", "jobs": 1}

    s = run_batch(jobs, mean_difference, progress=False, **batch_options(table))

    assert s.done == ("pair_00", "pair_01") and s.threads_per_worker == 1
    (kw,) = FakeSLURMCluster.made
    assert kw["queue"] == "short" and kw["walltime"] == "00:10:00" and kw["memory"] == "4GB"
    assert (kw["cores"], kw["processes"], kw["job_cpu"]) == (2, 2, 2)
    assert "export NUMBA_NUM_THREADS=1" in kw["job_script_prologue"]


# ---- no cluster needed ------------------------------------------------------------------------


def test_slurm_option_mapping():
    kw, jobs = slurm_cluster_kwargs({"cores": 32, "memory": "120GB", "walltime": "02:00:00",
                                     "queue": "compute", "account": "piv", "jobs": 3},
                                    threads_per_worker=4)
    assert jobs == 3
    # 8 worker processes of one dask thread each; SLURM books the 32 CPUs; numba gets 4
    assert (kw["cores"], kw["processes"], kw["job_cpu"]) == (8, 8, 32)
    assert "export NUMBA_NUM_THREADS=4" in kw["job_script_prologue"]
    assert "export OMP_NUM_THREADS=4" in kw["job_script_prologue"]
    assert kw["queue"] == "compute" and kw["account"] == "piv"
    kw, jobs = slurm_cluster_kwargs({"cores": 16, "memory": "64GB", "processes": 2},
                                    n_workers=5)
    assert (kw["processes"], jobs) == (2, 3)                  # 3 jobs hold 5 workers
    assert "export NUMBA_NUM_THREADS=8" in kw["job_script_prologue"]
    kw, _ = slurm_cluster_kwargs({"cores": 4, "memory": "8GB",
                                  "job_script_prologue": ["module load hdf5"]})
    assert kw["job_script_prologue"][-1] == "module load hdf5"

    for opts, words in (({"memory": "8GB"}, "cores"),
                        ({"cores": 4}, "memory"),
                        ({"cores": 4, "memory": "lots"}, "'lots'"),
                        ({"cores": 4, "memory": "8GB", "walltime": "2h"}, "walltime"),
                        ({"cores": 4, "memory": "8GB", "partition": "x"}, "'partition'"),
                        ({"cores": 4, "memory": "8GB", "processes": 3}, "needs 6 CPUs")):
        with pytest.raises(ConfigError, match=words):
            slurm_cluster_kwargs(opts, threads_per_worker=2 if "processes" in opts else None)


def test_batch_options_from_config_table():
    table = {"cluster": "local", "workers": 3, "threads_per_worker": None, "retries": 0,
             "queue": None, "cores": None, "memory": None, "walltime": None, "jobs": None}
    assert batch_options(table) == {"cluster": "local", "n_workers": 3, "retries": 0}
    with pytest.raises(ConfigError, match="unknown key 'nodes'"):
        batch_options({"nodes": 2})


def test_slurm_without_jobqueue_says_what_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "dask_jobqueue", None)   # import fails
    job = PairJob("p", "a.tif", "b.tif", tmp_path / "p.h5")
    with pytest.raises(ConfigError, match=r"pip install 'plenopiv\[hpc\]'"):
        run_batch([job], mean_difference, cluster="slurm",
                  cluster_options={"cores": 2, "memory": "1GB"})


def test_bad_arguments_are_rejected_before_anything_runs(tmp_path):
    stale = tmp_path / ".p.h5.abcdefgh.part"
    stale.write_bytes(b"")
    job = PairJob("p", "a.tif", "b.tif", tmp_path / "p.h5")
    cases = [
        (dict(cluster="pbs"), "cluster 'pbs': expected 'local', 'slurm' or a scheduler"),
        (dict(cluster="slurm://x"), "expected 'local', 'slurm'"),
        (dict(n_workers=0), "n_workers 0"),
        (dict(threads_per_worker="2"), "threads_per_worker '2'"),
        (dict(retries=-1), "retries -1: expected an integer >= 0"),
        (dict(cluster_options={"n_gpus": 1}), "unknown key 'n_gpus'"),
        (dict(cluster="tcp://h:8786", cluster_options={"memory_limit": "1GB"}),
         "unknown key 'memory_limit'"),
    ]
    for kwargs, words in cases:
        with pytest.raises(ConfigError, match=words):
            run_batch([job], mean_difference, **kwargs)
    with pytest.raises(ConfigError, match="job list is empty"):
        run_batch([], mean_difference)
    with pytest.raises(ConfigError, match="not callable"):
        run_batch([job], "mean_difference")
    with pytest.raises(ConfigError, match="same name 'p'"):
        run_batch([job, PairJob("p", "c.tif", "d.tif", tmp_path / "q.h5")], mean_difference)
    with pytest.raises(ConfigError, match="same output"):
        run_batch([job, PairJob("q", "c.tif", "d.tif", tmp_path / "p.h5")], mean_difference)
    with pytest.raises(ConfigError, match="HDF5 file ending in .h5"):
        PairJob("p", "a.tif", "b.tif", tmp_path / "p.npz")
    with pytest.raises(ConfigError, match="path separators"):
        PairJob("a/b", "a.tif", "b.tif", tmp_path / "p.h5")
    assert stale.exists()            # nothing was cleaned up by a rejected call


def test_discover_pairs_by_stem_by_order_and_per_file(tmp_path, rng):
    make_pairs(tmp_path / "images", 3, rng)
    jobs = discover_pairs("images/*_A.tif", "images/*_B.tif", out_dir="out", root=tmp_path)
    assert [j.name for j in jobs] == ["pair_00", "pair_01", "pair_02"]
    j = jobs[1]
    assert j.image_a == str(tmp_path / "images" / "pair_01_A.tif")
    assert j.image_b == str(tmp_path / "images" / "pair_01_B.tif")
    assert j.output == tmp_path / "out" / "pair_01.h5"

    # two cameras' folders with different names: no common wildcard part -> sorted order,
    # natural order (frame 2 before frame 10)
    for cam in ("A", "B"):
        (tmp_path / cam).mkdir()
        for k in (2, 10, 1):
            (tmp_path / cam / f"{cam}_{k}.tif").write_bytes(b"")
    jobs = discover_pairs("A/*.tif", "B/*.tif", out_dir="out", root=tmp_path)
    assert [(Path(j.image_a).name, Path(j.image_b).name) for j in jobs] == [
        ("A_1.tif", "B_1.tif"), ("A_2.tif", "B_2.tif"), ("A_10.tif", "B_10.tif")]
    assert [j.name for j in jobs] == ["A_1", "A_2", "A_10"]   # no common start: A's stem
    with pytest.raises(ConfigError, match="do not pair by their wildcard parts"):
        discover_pairs("A/*.tif", "B/*.tif", out_dir="out", root=tmp_path, pair_by="stem")

    # one HDF5 file per pair; its products must not overwrite it
    pairs = tmp_path / "pairs"
    for k in range(2):
        write_h5(pairs / f"run_{k}.h5", {"/image_a": np.eye(4) * (k + 1),
                                         "/image_b": np.eye(4) * (k + 2)})
    jobs = discover_pairs("pairs/*.h5", out_dir="vectors", root=tmp_path)
    assert [j.name for j in jobs] == ["run_0", "run_1"]
    assert read_image(jobs[1].image_b).max() == 3.0
    with pytest.raises(ConfigError, match="would overwrite an input image"):
        discover_pairs("pairs/*.h5", out_dir="pairs", root=tmp_path)


def test_discover_pairs_errors_name_the_problem(tmp_path, rng):
    make_pairs(tmp_path / "images", 3, rng)
    (tmp_path / "images" / "pair_01_B.tif").unlink()
    with pytest.raises(ConfigError, match=r"1 first exposures have no second.*pair_01_A"):
        discover_pairs("images/*_A.tif", "images/*_B.tif", out_dir="o", root=tmp_path)
    with pytest.raises(ConfigError, match="matches 3 files but pattern_b .* matches 2"):
        discover_pairs("images/*_A.tif", "images/*_B.tif", out_dir="o", root=tmp_path,
                       pair_by="order")
    with pytest.raises(ConfigError, match=r"pattern_b 'images/\*_C.tif' matches no file"):
        discover_pairs("images/*_A.tif", "images/*_C.tif", out_dir="o", root=tmp_path)
    with pytest.raises(ConfigError, match="expects one HDF5 file per pair"):
        discover_pairs("images/*_A.tif", out_dir="o", root=tmp_path)
    with pytest.raises(ConfigError, match="both match"):
        discover_pairs("images/*.tif", "images/*_B.tif", out_dir="o", root=tmp_path)
    with pytest.raises(ConfigError, match="pair_by 'name'"):
        discover_pairs("images/*_A.tif", "images/*_B.tif", out_dir="o", pair_by="name")


def test_completeness_mark(tmp_path):
    p = tmp_path / "product.h5"
    assert not is_complete(p)                             # missing
    p.write_bytes(b"\x89HDF\r\n\x1a\n truncated")
    assert not is_complete(p)                             # not readable
    write_h5(p, {"/x": np.arange(3)})
    assert not is_complete(p)                             # written, not marked
    mark_complete(p)
    assert is_complete(p)
    with h5py.File(p, "r+") as fh:
        fh.attrs[batch.COMPLETE_ATTR] = False
    assert not is_complete(p)
    write_h5(p, {"/x": np.arange(3)}, attrs={batch.COMPLETE_ATTR: True})  # one atomic write
    assert is_complete(p)


def test_summary_to_dict_is_plain_json():
    done = batch.JobResult("p", "done", "/x/p.h5", 1.5,
                           result={"rms": np.float32(0.25), "shape": np.array([2, 3]),
                                   "odd": object()})
    s = BatchSummary(done=("p",), skipped=(), failed=(), seconds=2.0, results=(done,))
    d = s.to_dict()
    assert json.loads(json.dumps(d)) == d
    r = d["results"][0]["result"]
    assert r["rms"] == 0.25 and r["shape"] == [2, 3] and r["odd"].startswith("<object")
    assert s.ok and s.n_jobs == 1 and d["n_done"] == 1


# ---- issue #14: keyed resume, stale temporaries, Ctrl-C, full disk --------------------------


def keyed_mean_difference(job: PairJob) -> dict:
    """The contract with an identity: stored in the product with the complete mark."""
    a = read_image(job.image_a).astype(np.float64)
    b = read_image(job.image_b).astype(np.float64)
    write_h5(job.output, {"/difference": b - a}, kind="test product")
    mark_complete(job.output, identity=job.identity)
    return {"mean_difference": float((b - a).mean())}


def slow_mean_difference(job: PairJob) -> dict:
    """The first two pairs take 1.5 s, the others 10 s: the test's Ctrl-C, sent once the
    second product exists, lands while a pair is running even on a machine so loaded that
    the test process waits seconds for the CPU."""
    import time

    time.sleep(1.5 if job.name in ("pair_00", "pair_01") else 10.0)
    return keyed_mean_difference(job)


def with_identity(jobs, settings="s1"):
    from dataclasses import replace

    from plenopiv.products.files import file_identity

    return [replace(j, identity={"settings": settings, "image_a": file_identity(j.image_a),
                                 "image_b": file_identity(j.image_b)}) for j in jobs]


def test_resume_recomputes_products_made_from_other_settings_or_inputs(tmp_path, rng):
    make_pairs(tmp_path / "images", 3, rng)
    jobs = with_identity(discover_pairs("images/*_A.tif", "images/*_B.tif", out_dir="out",
                                        root=tmp_path))
    first = run_batch(jobs, keyed_mean_difference, n_workers=1, progress=False)
    assert first.done == ("pair_00", "pair_01", "pair_02") and first.recomputed == ()
    assert batch.product_identity(jobs[0].output) == dict(jobs[0].identity)

    # the same settings and inputs: nothing to do (no cluster behind this address)
    same = run_batch(jobs, keyed_mean_difference, cluster="tcp://127.0.0.1:9", progress=False)
    assert same.skipped == ("pair_00", "pair_01", "pair_02")

    # another pair's complete product copied over a name; one made before identities; and
    # an image edited since
    out = tmp_path / "out"
    (out / "pair_00.h5").write_bytes((out / "pair_01.h5").read_bytes())
    with h5py.File(out / "pair_02.h5", "r+") as fh:
        del fh.attrs[batch.IDENTITY_ATTR]
    assert is_complete(out / "pair_00.h5") and is_complete(out / "pair_02.h5")
    second = run_batch(jobs, keyed_mean_difference, n_workers=1, progress=False)
    assert second.done == ("pair_00", "pair_02") and second.skipped == ("pair_01",)
    reasons = dict(second.recomputed)
    assert reasons["pair_00"] == "made with other first image, second image"
    assert "records no identity" in reasons["pair_02"]
    d = second.to_dict()
    assert d["n_recomputed"] == 2 and d["recomputed"][0]["name"] == "pair_00"
    assert h5py.File(out / "pair_00.h5")["/difference"][()].mean() == 0.0   # pair 0's own

    # the settings changed: every pair is recomputed, and the summary says why
    third = run_batch(with_identity(jobs, settings="s2"), keyed_mean_difference, n_workers=1,
                      progress=False)
    assert third.done == ("pair_00", "pair_01", "pair_02")
    assert {r for _, r in third.recomputed} == {"made with other settings"}
    on_disk = json.loads((out / batch.SUMMARY_NAME).read_text())
    assert on_disk["n_recomputed"] == 3

    # a process that does not store the identity breaks the contract: failed, not looping
    broken = run_batch(with_identity(jobs, settings="s3"), mean_difference, n_workers=1,
                       progress=False)
    assert len(broken.failed) == 3 and "does not record the job's identity" in broken.failed[0][1]


def test_temporaries_of_every_product_of_a_pair_are_removed(tmp_path, rng):
    make_pairs(tmp_path / "images", 2, rng)
    jobs = discover_pairs("images/*_A.tif", "images/*_B.tif", out_dir="out", root=tmp_path,
                          output_name="{name}_vectors.h5")
    out = tmp_path / "out"
    out.mkdir()
    for j in jobs:
        write_h5(j.output, {"/x": np.zeros(2)}, attrs={batch.COMPLETE_ATTR: True})
    stale = [".pair_00_volume_A.h5.k1ll3d00.part", ".pair_00_volume_B.h5.k1ll3d01.part",
             ".pair_00_vectors.vti.k1ll3d02.part", ".pair_00_vectors.vti.k1ll3d03.part.vti",
             ".pair_01_vectors.h5.k1ll3d04.part", ".pair_01_vectors.png.k1ll3d05.part"]
    for name in stale:
        (out / name).write_bytes(b"half")
    keep = out / ".other_vectors.h5.abcdefgh.part"      # not one of this batch's pairs
    keep.write_bytes(b"")
    s = run_batch(jobs, mean_difference, cluster="tcp://127.0.0.1:9", progress=False)
    assert s.skipped == ("pair_00", "pair_01")
    assert sorted(Path(p).name for p in s.removed_parts) == sorted(stale)
    assert not any((out / n).exists() for n in stale) and keep.exists()


INTERRUPTED_BATCH = """
import signal
import sys
# Ctrl-C as at a terminal, whatever this test process's own SIGINT disposition (a child
# started while its parent ignores SIGINT inherits the ignore and Python keeps it)
signal.signal(signal.SIGINT, signal.default_int_handler)
sys.path.insert(0, {tests!r})
from test_batch import slow_mean_difference, with_identity
from plenopiv.batch import BatchInterrupted, discover_pairs, run_batch
from plenopiv.cli import sigterm_as_interrupt
jobs = with_identity(discover_pairs("images/*_A.tif", "images/*_B.tif", out_dir="out",
                                    root={root!r}))
try:
    with sigterm_as_interrupt():
        run_batch(jobs, slow_mean_difference, n_workers=1, progress=False)
except BatchInterrupted as exc:
    print("INTERRUPTED", exc, flush=True)
    sys.exit(exc.exit_status)
print("FINISHED", flush=True)
"""


@pytest.mark.parametrize(("stop", "status", "said"), [
    ("SIGINT", 130, "interrupted (Ctrl-C)"), ("SIGTERM", 143, "terminated (SIGTERM)")])
def test_ctrl_c_and_sigterm_stop_cleanly_write_the_summary_and_resume(tmp_path, rng, stop,
                                                                      status, said):
    """Ctrl-C, and SIGTERM (SLURM's cancel and wall time) the same way: exit 130 or 143."""
    import signal
    import subprocess
    import time

    make_pairs(tmp_path / "images", 6, rng)
    out = tmp_path / "out"
    env = dict(os.environ)
    src = str(Path(__file__).resolve().parents[2] / "src")
    env["PYTHONPATH"] = src + os.pathsep + env.get("PYTHONPATH", "")
    code = INTERRUPTED_BATCH.format(tests=str(Path(__file__).parent), root=str(tmp_path))
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, start_new_session=True)
    deadline = time.time() + 120
    while time.time() < deadline and not (out / "pair_01.h5").exists():
        time.sleep(0.1)
    assert (out / "pair_01.h5").exists(), proc.communicate(timeout=30)
    time.sleep(0.5)                               # pair_00 is reported done by now
    os.killpg(proc.pid, getattr(signal, stop))  # reaches the whole process group
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == status, (stdout, stderr)
    assert f"INTERRUPTED {said}" in stdout and "Traceback" not in stderr
    summary = json.loads((out / batch.SUMMARY_NAME).read_text())
    assert summary["n_done"] >= 1 and summary["n_interrupted"] >= 1
    assert summary["n_done"] + summary["n_interrupted"] + summary["n_failed"] == 6
    assert parts(out) == []
    for name in summary["done"]:
        assert is_complete(out / f"{name}.h5")

    # the same command again resumes: the finished pairs are skipped, the rest computed
    jobs = with_identity(discover_pairs("images/*_A.tif", "images/*_B.tif", out_dir="out",
                                        root=tmp_path))
    again = run_batch(jobs, keyed_mean_difference, n_workers=2, progress=False)
    assert set(again.skipped) >= set(summary["done"])
    assert len(again.done) + len(again.skipped) == 6 and again.ok


def test_a_full_disk_is_an_error_that_leaves_nothing_marked_complete(tmp_path, monkeypatch):
    """ENOSPC part way through a product: a WriteError naming the file, and neither the
    product, its .vti nor a temporary is left."""
    import errno

    from plenopiv.errors import WriteError
    from plenopiv.products.vectors import VectorResult

    n = (2, 3, 4)
    vec = VectorResult(np.arange(4.0), np.arange(3.0), np.arange(2.0), *(np.ones(n),) * 3,
                       np.ones(n, bool), np.ones(n), dt=1e-3)
    calls = {"n": 0}
    create = h5py.Group.create_dataset

    def full_after_three(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] > 3:
            raise OSError(errno.ENOSPC, "No space left on device")
        return create(self, *args, **kwargs)

    monkeypatch.setattr(h5py.Group, "create_dataset", full_after_three)
    with pytest.raises(WriteError, match=r"vectors\.h5' failed: no space left on device"):
        vec.save(tmp_path / "vectors.h5", vtk=True, extra_attrs={batch.COMPLETE_ATTR: True})
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["vectors.vti"]   # the .vti came first
    (tmp_path / "vectors.vti").unlink()

    # the disk fills while the .vti is written: no stray temporary, no product
    import pyevtk.hl

    def full_vti(path, **kwargs):
        Path(path + ".vti").write_bytes(b"<VTKFile half")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pyevtk.hl, "imageToVTK", full_vti)
    with pytest.raises(WriteError, match="no space left on device"):
        vec.save(tmp_path / "vectors.h5", vtk=True, extra_attrs={batch.COMPLETE_ATTR: True})
    assert list(tmp_path.iterdir()) == []

    # in a batch: the pair fails with the reason, the others go on, nothing marked complete
    monkeypatch.undo()
    assert not is_complete(tmp_path / "vectors.h5")


def enospc_on_pair_01(job: PairJob) -> dict:
    import errno

    if job.name == "pair_01":
        raise OSError(errno.ENOSPC, "No space left on device")
    return mean_difference(job)


def test_full_disk_pair_fails_alone(tmp_path, rng):
    make_pairs(tmp_path / "images", 3, rng)
    jobs = discover_pairs("images/*_A.tif", "images/*_B.tif", out_dir="out", root=tmp_path)
    s = run_batch(jobs, enospc_on_pair_01, n_workers=1, progress=False)
    assert s.done == ("pair_00", "pair_02") and not s.ok
    assert s.failed[0][0] == "pair_01" and "No space left on device" in s.failed[0][1]
    assert not (tmp_path / "out" / "pair_01.h5").exists()


@pytest.mark.skipif(sys.platform != "linux", reason="glibc's allocator, Linux's page faults")
@pytest.mark.parametrize("user_env", [(), (("MALLOC_TRIM_THRESHOLD_", "131072"),)])
def test_a_worker_reuses_freed_memory_unless_the_user_chose_otherwise(tmp_path, rng, monkeypatch,
                                                                    user_env):
    """A dask nanny starts each worker with ``MALLOC_TRIM_THRESHOLD_=65536``, which hands
    every freed array back and faults the next one in again page by page (a full-size pair
    of ``plenopiv run`` took a third longer). The worker's memory follows what the user set
    where the command runs, which the pair's process carries; not that variable."""
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    monkeypatch.delenv("MALLOC_MMAP_MAX_", raising=False)
    make_pairs(tmp_path / "images", 1, rng)
    jobs = discover_pairs("images/*_A.tif", "images/*_B.tif", out_dir="out", root=tmp_path)
    s = run_batch(jobs, AllocatorProbe(user_env), n_workers=1, threads_per_worker=1,
                  progress=False)
    (r,) = s.results
    assert r.status == "done", r.error
    pages = 9 * (1 << 26) // 4096                  # 9 arrays of 64 MB in 4 kB pages
    if user_env:
        assert r.result["faults"] > 0.5 * pages    # the allocator as the user chose it
    else:
        assert r.result["faults"] < 0.05 * pages   # reused, whatever the nanny set


def test_slurm_workers_start_with_one_malloc_arena_unless_the_user_chose(monkeypatch):
    for key in ("MALLOC_ARENA_MAX", "MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_MAX_"):
        monkeypatch.delenv(key, raising=False)
    opts = {"cores": 4, "memory": "16GB"}
    kw, _ = slurm_cluster_kwargs(opts, threads_per_worker=2)
    assert "export MALLOC_ARENA_MAX=1" in kw["job_script_prologue"]
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "131072")
    kw, _ = slurm_cluster_kwargs(opts, threads_per_worker=2)
    assert not any("MALLOC" in line for line in kw["job_script_prologue"])
