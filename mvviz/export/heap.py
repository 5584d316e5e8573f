"""Give the C heap's free pages back to the system between an export's chunks.

The rerun export skins meshes (torch) and hands multi-MB columns to rerun's writer
threads chunk after chunk. glibc's malloc raises its mmap threshold each time such a
buffer is freed (the "dynamic" threshold, up to 32 MB), so the later ones are carved from
the heap arenas instead of their own mappings, and once freed their pages stay resident
behind whatever small allocation lands above them: the export's memory grew with the
frames exported although nothing was kept (after each chunk of a 10-person dome's bodies:
145 -> 186 MB over 1,000 frames; ~200 KB a frame of the sample). ``malloc_trim(0)`` hands
every whole free page of every arena back (``madvise``); it is called once the arenas
hold more than :data:`KEEP_FREE_BYTES` free, so memory stays bounded (84-86 MB after every
chunk of the same export; 58 / 78-81 trimming after every chunk) while the pages a chunk
frees are mostly reused by the next without a trim and a fault each time.

Measured against the other fix, a fixed mmap threshold (``mallopt(M_MMAP_THRESHOLD)``,
which also stops the growth): that one maps and faults every big buffer anew and made
the sample's export ~35 % slower (``bench/bench_export_memory.py`` has the baseline
without the trim).
"""

from __future__ import annotations

import ctypes
import functools
import sys

KEEP_FREE_BYTES = 64 << 20
"""Free bytes the arenas may hold before :func:`release_free_heap` trims them."""


class _MallInfo2(ctypes.Structure):
    """glibc's ``struct mallinfo2`` (2.33+): sizes in bytes, summed over every arena."""

    _fields_ = [
        (name, ctypes.c_size_t)
        for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks",
                     "uordblks", "fordblks", "keepcost")
    ]  # fmt: skip


@functools.cache
def _glibc():
    """(malloc_trim, mallinfo2 or None), or None where the C library has no
    ``malloc_trim`` (macOS, Windows, musl)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None)
        trim = libc.malloc_trim
    except (OSError, AttributeError):
        return None
    info = getattr(libc, "mallinfo2", None)  # glibc < 2.33: trim every time
    if info is not None:
        info.restype = _MallInfo2
    return trim, info


def release_free_heap(keep_free: int = KEEP_FREE_BYTES) -> bool:
    """Return the C heap's free pages to the system once its arenas hold more than
    ``keep_free`` bytes free (0: always). True if trimmed; False if not needed or where
    the C library has no ``malloc_trim`` (nothing done)."""
    calls = _glibc()
    if calls is None:
        return False
    trim, info = calls
    if keep_free > 0 and info is not None and info().fordblks <= keep_free:
        return False
    trim(0)
    return True
