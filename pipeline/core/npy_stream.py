"""``.npy`` files written a piece at a time, with bounded memory.

Two writers for the arrays of a long run that must not all sit in RAM:

* :class:`NpyRowAppender`: rows appended to a file whose row count is known only at the
  end (person-frames, affinity edges). The header is reserved at open and rewritten with
  the final shape at :meth:`~NpyRowAppender.close`, so no second pass copies the data.
* :func:`open_npy_for_writing`: a file of known shape, memory-mapped for writing slices
  (detection rows, track arrays); :func:`release_pages` hands the written pages back to
  the page cache so they stop counting in this process's resident memory.

Both write the standard format (version 1.0): ``np.load`` reads the files, mapped or not.
"""

from __future__ import annotations

import dataclasses
import mmap
import os
from pathlib import Path

import numpy as np

_MAGIC = b"\x93NUMPY\x01\x00"
_HEADER_BYTES = 128  # the whole preamble + header, a multiple of 64 as numpy aligns it


def _header(dtype: np.dtype, shape: tuple[int, ...]) -> bytes:
    """The v1.0 preamble and header for (dtype, shape), padded to :data:`_HEADER_BYTES`."""
    descr = np.lib.format.dtype_to_descr(np.dtype(dtype))
    text = f"{{'descr': {descr!r}, 'fortran_order': False, 'shape': {tuple(map(int, shape))!r}, }}"
    room = _HEADER_BYTES - len(_MAGIC) - 2  # the 2-byte little-endian header length
    if len(text) + 1 > room:
        raise ValueError(f"shape {shape} does not fit the reserved .npy header")
    body = text.ljust(room - 1).encode("latin1") + b"\n"
    return _MAGIC + room.to_bytes(2, "little") + body


class NpyRowAppender:
    """Rows of shape ``row_shape`` and ``dtype`` appended to ``path`` (a new file).

    The file is a valid ``.npy`` once :meth:`close` has run; before, its header says 0
    rows of a huge reserved width, so a half-written file is never read as complete.
    """

    def __init__(self, path: str | os.PathLike, dtype, row_shape: tuple[int, ...] = ()):
        self.path = Path(path)
        self.dtype = np.dtype(dtype)
        self.row_shape = tuple(int(s) for s in row_shape)
        self.rows = 0
        _header(self.dtype, (10**15, *self.row_shape))  # fails now if a final one cannot fit
        self._fh = open(self.path, "wb")  # noqa: SIM115 - closed by close()
        self._fh.write(_header(self.dtype, (0, *self.row_shape)))

    def append(self, rows: np.ndarray) -> None:
        """Append ``rows``: (n, *row_shape), cast to the file's dtype."""
        a = np.ascontiguousarray(rows, dtype=self.dtype)
        if a.shape[1:] != self.row_shape:
            raise ValueError(
                f"{self.path.name}: rows of shape {self.row_shape} expected, got {a.shape[1:]}"
            )
        if a.size:
            self._fh.write(a.reshape(-1).view(np.uint8).data)
        self.rows += a.shape[0]

    def discard(self) -> None:
        """Close the file as it is (its header still says 0 rows)."""
        self._fh.close()

    def close(self) -> None:
        """Write the final header (the row count) and close the file."""
        if self._fh.closed:
            return
        self._fh.flush()
        self._fh.seek(0)
        self._fh.write(_header(self.dtype, (self.rows, *self.row_shape)))
        self._fh.close()


def open_npy_for_writing(path: str | os.PathLike, dtype, shape: tuple[int, ...], fill=None):
    """A new ``.npy`` file of ``shape`` memory-mapped read-write (``np.memmap``); with
    ``fill``, every element set to it first (in slices of the first axis, pages released)."""
    out = np.lib.format.open_memmap(Path(path), mode="w+", dtype=dtype, shape=tuple(shape))
    if fill is not None and out.size:
        step = max(1, (64 << 20) // max(out[:1].nbytes, 1))
        for i in range(0, out.shape[0], step):
            out[i : i + step] = fill
            release_pages(out)
    return out


def _mapping(arr: np.ndarray) -> mmap.mmap | None:
    """The ``mmap`` under ``arr`` (through its chain of bases), if any."""
    while arr is not None:
        if isinstance(arr, mmap.mmap):
            return arr
        m = getattr(arr, "_mmap", None)
        if isinstance(m, mmap.mmap):
            return m
        arr = getattr(arr, "base", None)
    return None


def is_mapped(arr: np.ndarray) -> bool:
    """Whether ``arr`` views a memory-mapped file."""
    return _mapping(arr) is not None


def mapped_arrays(*objs, depth: int = 4) -> list[np.ndarray]:
    """One array per distinct file map found in ``objs`` (ndarrays, dataclasses, dicts,
    lists and tuples of them, ``depth`` levels deep): what :func:`release_pages` is given
    to hand a scene's or its results' read pages back, however they are nested."""
    found: dict[int, np.ndarray] = {}

    def walk(obj, level: int) -> None:
        if isinstance(obj, np.ndarray):
            m = _mapping(obj)
            if m is not None:
                found.setdefault(id(m), obj)
        elif level < depth:
            if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
                items = (getattr(obj, f.name) for f in dataclasses.fields(obj))
            elif isinstance(obj, dict):
                items = obj.values()
            elif isinstance(obj, list | tuple):
                items = obj
            else:
                return
            for item in items:
                walk(item, level + 1)

    for obj in objs:
        walk(obj, 0)
    return list(found.values())


def release_pages(arr: np.ndarray) -> bool:
    """Write back and drop from this process's resident set the pages of the file map
    under ``arr`` (the data stays in the file and the page cache; a later read maps it in
    again). Why: pages of a shared file map that were touched stay in the process's RSS
    until unmapped, so a map read or written front to back would otherwise end holding
    the whole file. Returns False if ``arr`` is not memory-mapped (nothing to do)."""
    m = _mapping(arr)
    if m is None or m.closed:
        return False
    if m.size():
        if isinstance(arr, np.memmap) and arr.mode in ("r+", "w+"):
            m.flush()
        m.madvise(mmap.MADV_DONTNEED)
    return True
