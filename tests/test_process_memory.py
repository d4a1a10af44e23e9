"""The command's and batch workers' own process: freed memory reused, not faulted in again."""

from __future__ import annotations

import platform
import subprocess
import sys

import pytest

# Allocate, touch and free a 64 MB array (above glibc's 32 MB mmap ceiling) ten times and
# count the page faults of the last nine: with glibc's defaults each one is a fresh mapping
# faulted in page by page (16,384 faults of 4 kB pages, NumPy's huge-page advice off as in
# the command's process); reused, they fault nothing.
_FAULTS = """
import resource, sys
import numpy as np
from plenopiv.resources import prefer_small_pages, reuse_freed_memory
prefer_small_pages()
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
def test_an_allocator_setting_in_the_environment_is_the_users(monkeypatch):
    import os

    env = {**os.environ, "MALLOC_TRIM_THRESHOLD_": "131072"}
    changed, faults = _faults("on", env)
    assert not changed
    assert faults > 0.5 * 9 * (1 << 26) // 4096
