"""Give the C heap's free pages back to the system between an export's chunks.

The rerun export skins meshes (torch) and hands multi-MB columns to rerun's writer
threads chunk after chunk. glibc's malloc raises its mmap threshold each time such a
buffer is freed (the "dynamic" threshold, up to 32 MB), so the later ones are carved from
the heap arenas instead of their own mappings, and once freed their pages stay resident
behind whatever small allocation lands above them: the export's peak memory grew with
the frames exported (~200 KB a frame of the sample, ~85 KB of a 20-person dome) although
nothing was kept. ``malloc_trim(0)`` hands every whole free page of every arena back
(``madvise``): after each chunk the export's memory is back to one chunk's.

Measured against the other fix, a fixed mmap threshold (``mallopt(M_MMAP_THRESHOLD)``,
which also stops the growth): that one maps and faults every big buffer anew and made
the sample's export ~35 % slower; a trim per chunk costs a few milliseconds
(``bench/bench_export_memory.py``).
"""

from __future__ import annotations

import ctypes
import functools
import sys


@functools.cache
def _malloc_trim():
    """glibc's ``malloc_trim``, or None (macOS, Windows, musl: no such call)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        return None


def release_free_heap() -> bool:
    """Return the C heap's free pages to the system; False where the C library has no
    ``malloc_trim`` (nothing done)."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True
