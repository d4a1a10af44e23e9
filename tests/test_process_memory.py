"""The command's and batch workers' own process: freed memory reused, not faulted in again."""

from __future__ import annotations

import platform
import subprocess
import sys

import pytest

from small_case import volume_script

# Allocate, touch and free a 64 MB array (above glibc's 32 MB mmap ceiling) ten times and
# count the page faults of the last nine: with glibc's defaults each one is a fresh mapping
# faulted in page by page (16,384 faults of 4 kB pages, NumPy's huge-page advice off as in
# the command's process); reused, they fault nothing.
_FAULTS = """
import resource, sys
import numpy as np
from plenopiv.resources import prefer_small_pages, reuse_freed_memory
prefer_small_pages()
if sys.argv[1] == "command":             # the plenopiv command sets its own process up
    import contextlib, io
    from plenopiv.cli import main
    with contextlib.redirect_stdout(io.StringIO()):
        main(["presets"])
    changed = True
else:
    changed = reuse_freed_memory() if sys.argv[1] == "on" else False
np.ones(1 << 24, np.float32)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(9):
    a = np.ones(1 << 24, np.float32)
    del a
print(changed, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(mode: str, env: dict | None = None) -> tuple[bool, int]:
    out = subprocess.run([sys.executable, "-c", _FAULTS, mode], capture_output=True,
                         text=True, check=True, env=env).stdout.split()
    return out[0] == "True", int(out[1])


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_freed_arrays_are_reused_without_faulting_them_in_again():
    changed, reused = _faults("on")
    _, fresh = _faults("off")
    pages = 9 * (1 << 26) // 4096                  # 9 arrays of 64 MB in 4 kB pages
    assert changed
    assert fresh > 0.5 * pages                     # the default: each array faulted in anew
    assert reused < 0.05 * pages


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_the_command_reuses_what_it_frees():
    """Any plenopiv command sets its process up so (the batch workers' processors do the
    same, workflow/worker.py)."""
    _, faults = _faults("command")
    assert faults < 0.05 * 9 * (1 << 26) // 4096


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_an_allocator_setting_in_the_environment_is_the_users(monkeypatch):
    import os

    env = {**os.environ, "MALLOC_TRIM_THRESHOLD_": "131072"}
    changed, faults = _faults("on", env)
    assert not changed
    assert faults > 0.5 * 9 * (1 << 26) // 4096


_HOLE = """
import numpy as np
from plenopiv.resources import prefer_small_pages, release_freed_memory, reuse_freed_memory
prefer_small_pages()
reuse_freed_memory()
def rss():
    return int(open("/proc/self/status").read().split("VmRSS:")[1].split()[0]) * 1024
big = np.ones(50 << 20, np.float32)         # 200 MB from the heap
above = np.ones(1 << 20, np.float32)        # 4 MB above it: the freed 200 MB become a hole
del big
held = rss()
release_freed_memory()
print(held - rss())
"""


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="malloc_trim is glibc's")
def test_a_stage_hands_back_the_holes_earlier_stages_left():
    """Reused memory stays in the heap, holes included; a stage of several GB first hands
    them back, so that they add nothing to its peak."""
    out = subprocess.run([sys.executable, "-c", _HOLE], capture_output=True, text=True,
                         check=True).stdout
    assert int(out.split()[-1]) > 0.9 * (200 << 20)


_VOLUME = """
import sys
from plenopiv.resources import own_process_memory
if sys.argv[1] == "own":
    own_process_memory()
""" + volume_script(n_particles=120, seed=3) + """
import hashlib
h = hashlib.sha256(np.ascontiguousarray(r.volume).tobytes())
h.update(np.ascontiguousarray(r.particle_position).tobytes())
print(h.hexdigest())
"""


def test_the_memory_handling_changes_no_result():
    """Where the arrays come from is nothing physical: the volume and the particles of a
    process set up as the command's are those of a plain one, to the bit."""
    runs = [subprocess.run([sys.executable, "-c", _VOLUME, mode], capture_output=True,
                           text=True, check=True).stdout.split()[-1]
            for mode in ("own", "plain")]
    assert runs[0] == runs[1]
