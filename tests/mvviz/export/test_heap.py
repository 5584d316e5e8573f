"""mvviz.export.heap: freed buffers stuck in glibc's heap go back to the system."""

from __future__ import annotations

import subprocess
import sys

import pytest

from mvviz.export.heap import _glibc, release_free_heap

# What the export's chunks do to glibc's heap, in small: a big buffer freed raises the
# mmap threshold, so the next 4 MB buffers come from the heap, and small allocations
# above them keep the heap from shrinking when they are freed.
FRAGMENT = """
import ctypes, sys
import numpy as np
from mvviz.export.heap import release_free_heap

def rss_mb():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024

first = np.ones(8 << 17)  # 8 MB
del first
base = rss_mb()
held, pins = [], []
for _ in range(50):
    held.append(np.ones(4 << 17))  # 4 MB each, touched
    pins.append(ctypes.create_string_buffer(4096))
del held
freed = rss_mb()
done = release_free_heap()
print(base, freed, rss_mb(), done)
"""


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim")
def test_freed_buffers_held_by_the_heap_are_released():
    out = subprocess.run(
        [sys.executable, "-c", FRAGMENT], capture_output=True, text=True, check=True
    ).stdout.split()
    base, freed, after = map(float, out[:3])
    assert out[3] == "True"
    # 200 MB were freed but stayed resident (what grew the export's memory) ...
    assert freed - base > 150, (base, freed)
    # ... and are given back
    assert after - base < 30, (base, freed, after)


def test_release_free_heap_is_safe_to_call_often():
    # whether a call trims depends on what the process freed before (other tests): only
    # that it answers, every time, and that the limit decides
    assert all(isinstance(release_free_heap(), bool) for _ in range(6))
    calls = _glibc()
    if calls is not None:  # glibc
        assert release_free_heap(keep_free=0) is True  # always trims
        if calls[1] is not None:  # mallinfo2 tells how much is free: never that much
            assert release_free_heap(keep_free=1 << 62) is False
