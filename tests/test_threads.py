"""Serial kernels run on slices by threads (plenopiv._threads).

Every kernel run by :func:`run_slices` writes disjoint parts of its output for disjoint
slices, so the number of slices cannot change a single bit of the result.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from plenopiv._threads import run_slices, slices
from plenopiv.errors import Terminated
from plenopiv.reconstruction._kernels import lattice as lk
from plenopiv.synthetic import _kernels as sk


@pytest.mark.parametrize("n", [0, 1, 2, 5, 17, 1000])
@pytest.mark.parametrize("parts", [1, 2, 3, 8])
def test_slices_cover_the_range_once_in_order(n, parts):
    got = slices(n, parts)
    assert len(got) <= parts
    assert all(hi > lo for lo, hi in got)
    covered = [i for lo, hi in got for i in range(lo, hi)]
    assert covered == list(range(n))
    sizes = [hi - lo for lo, hi in got]
    assert not sizes or max(sizes) - min(sizes) <= 1


def test_an_error_in_any_slice_is_raised_after_all_slices_ended():
    done = []

    def kernel(lo, hi):
        done.append(lo)
        if lo > 0:
            raise ValueError(f"slice {lo}")

    with pytest.raises(ValueError, match="slice"):
        run_slices(kernel, 30, parts=3)
    assert sorted(done) == [0, 10, 20]


@pytest.mark.parametrize("interrupt", [KeyboardInterrupt, Terminated])
def test_an_interrupt_of_the_calling_slice_is_raised_without_waiting_for_the_others(interrupt):
    """The calling thread's slice is interrupted while it holds a lock the other slices wait
    on (as numba's compiler holds llvmlite's while a kernel loads): the interrupt comes out at
    once instead of waiting for slices that can never end. An error that is no interrupt
    still waits for every slice (the test above)."""
    held = threading.Lock()
    started = threading.Event()

    def kernel(lo, hi):
        if lo == 0:
            held.acquire()          # never released: the interrupt comes inside it
            started.set()
            raise interrupt()
        started.wait()
        with held:
            pass

    outcome = []

    def call():
        try:
            run_slices(kernel, 20, parts=2)
        except BaseException as exc:  # noqa: BLE001 - what came out is the result
            outcome.append(exc)

    caller = threading.Thread(target=call, daemon=True)
    caller.start()
    caller.join(timeout=30)
    hung = caller.is_alive()
    held.release()                  # the waiting slice ends, the pool is free again
    caller.join(timeout=30)
    assert not hung, "run_slices waited for a slice that waits on the interrupted one"
    assert len(outcome) == 1 and isinstance(outcome[0], interrupt)


def test_the_lattice_kernels_give_the_same_bits_on_any_number_of_slices():
    rng = np.random.default_rng(3)
    nz, ny, nx, ncol, kmax = 5, 7, 9, 11, 3
    volume = rng.random((nz, ny, nx)).astype(np.float32)
    xs = rng.integers(0, nx - kmax, (nz, ncol))
    xc = rng.integers(1, kmax + 1, (nz, ncol))
    xw = rng.random((nz, ncol, kmax)).astype(np.float32)
    outs = []
    for parts in (1, 2, 4, nz * ny):
        out = np.full((nz, ny, ncol), np.nan, np.float32)
        run_slices(lk.contract_x, nz * ny, volume, xs, xc, xw, out, parts=parts)
        back = np.full((nz, ny, nx), np.nan, np.float32)
        run_slices(lk.spread_x, nz * ny, out, xs, xc, xw, back, parts=parts)
        outs.append((out, back))
    want = np.zeros((nz, ny, ncol))
    for k in range(nz):
        for c in range(ncol):
            for j in range(xc[k, c]):
                want[k, :, c] += xw[k, c, j] * volume[k, :, xs[k, c] + j]
    np.testing.assert_allclose(outs[0][0], want, rtol=1e-5)
    for out, back in outs[1:]:
        np.testing.assert_array_equal(out, outs[0][0])
        np.testing.assert_array_equal(back, outs[0][1])


def test_the_renderer_gives_the_same_bits_on_any_number_of_slices(small_camera):
    from plenopiv.synthetic.tracer import _Render

    rng = np.random.default_rng(4)
    r = _Render(small_camera, None, "bilinear", 0.0, (0.0, 0.0))
    z = -small_camera.object_distance
    src = np.column_stack([rng.uniform(-1e-3, 1e-3, (23, 2)), z + rng.uniform(-1e-3, 1e-3, 23)])
    images = []
    for parts in (1, 2, 3):
        out = np.zeros((3,) + r.out.shape[1:])
        run_slices(sk.render_sources, 3, src, np.ones(23), np.zeros(2), 16, 5, 0,
                   np.array([0.0, 0.0, 1.0]), r.g, out, parts=parts)
        images.append(out)
    assert images[0].sum() > 0
    for img in images[1:]:
        np.testing.assert_array_equal(img, images[0])
