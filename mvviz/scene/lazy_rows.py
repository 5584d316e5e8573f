"""Per-detection arrays the viewer computes when a frame asks for them, not at start-up.

At 10,000 frames x 31 cameras x 20 people a scene has ~6 M detection rows: rays and
image-plane points of every detected joint for the whole sequence would be ~4 GB and
minutes of work before the first frame. :class:`RowBlocks` computes them for blocks of
consecutive rows the first time a row of the block is indexed (a frame's rows are
consecutive, so a frame change computes one or two blocks) and keeps the most recent
blocks; :class:`LazyRows` indexes one of its arrays like the full (N, ...) array would be.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable

import numpy as np

BLOCK_ROWS = 1024  # ~1-2 frames of a 31-camera x 20-person scene
CACHED_BLOCKS = 256  # ~0.26 M rows, ~50 MB of rays and points at 17 joints


class RowBlocks:
    """``compute(rows) -> tuple of (len(rows), ...) arrays`` for rows ``0..num_rows-1``,
    evaluated a block of :data:`BLOCK_ROWS` rows at a time and kept for the most recent
    :data:`CACHED_BLOCKS` blocks (thread-safe: the render and image threads share it)."""

    def __init__(
        self,
        compute: Callable[[np.ndarray], tuple[np.ndarray, ...]],
        num_rows: int,
        *,
        block_rows: int | None = None,
        cached_blocks: int | None = None,
    ) -> None:
        self.compute = compute
        self.num_rows = int(num_rows)
        self.block_rows = int(block_rows or BLOCK_ROWS)  # read here: tests may set them
        self.cached_blocks = int(cached_blocks or CACHED_BLOCKS)
        self.blocks_computed = 0  # how many block computations ran (tests, benchmarks)
        self._cache: OrderedDict[int, tuple[np.ndarray, ...]] = OrderedDict()
        self._lock = threading.Lock()

    def _block(self, b: int) -> tuple[np.ndarray, ...]:
        with self._lock:
            hit = self._cache.get(b)
            if hit is not None:
                self._cache.move_to_end(b)
                return hit
        lo = b * self.block_rows
        out = self.compute(np.arange(lo, min(lo + self.block_rows, self.num_rows)))
        with self._lock:
            self.blocks_computed += 1
            self._cache[b] = out
            while len(self._cache) > self.cached_blocks:
                self._cache.popitem(last=False)
        return out

    def gather(self, rows: np.ndarray, which: int) -> np.ndarray:
        """Array ``which`` of ``compute``'s output at ``rows`` (any shape of int rows)."""
        rows = np.asarray(rows, dtype=np.int64)
        if rows.size and (rows.min() < -self.num_rows or rows.max() >= self.num_rows):
            raise IndexError(f"row index out of range for {self.num_rows} rows")
        flat = np.where(rows < 0, rows + self.num_rows, rows).ravel()
        block = flat // self.block_rows
        if len(flat) == 0:  # nothing to gather: the empty result of the right shape
            empty = self.compute(np.zeros(0, np.int64))[which]
            return empty.reshape(rows.shape + empty.shape[1:])
        out = None
        lo = int(block.min())  # bincount, not np.unique: ~100x faster on a frame's rows
        for b in lo + np.flatnonzero(np.bincount(block - lo)):
            sel = block == b
            part = self._block(int(b))[which]
            if out is None:
                out = np.empty((len(flat),) + part.shape[1:], part.dtype)
            out[sel] = part[flat[sel] - b * self.block_rows]
        return out.reshape(rows.shape + out.shape[1:])

    def array(self, which: int) -> LazyRows:
        return LazyRows(self, which)


class LazyRows:
    """Array ``which`` of a :class:`RowBlocks`, indexed like an (N, ...) array by rows
    first: ``x[rows]``, ``x[rows, joints]``. ``np.asarray(x)`` computes every row (for
    tests and small scenes; the viewer never does)."""

    def __init__(self, blocks: RowBlocks, which: int) -> None:
        self.blocks = blocks
        self.which = which

    def __len__(self) -> int:
        return self.blocks.num_rows

    def __getitem__(self, key):
        rows, rest = (key[0], key[1:]) if isinstance(key, tuple) else (key, ())
        if isinstance(rows, slice):
            rows = np.arange(self.blocks.num_rows)[rows]
        rows = np.asarray(rows)
        if rows.dtype == bool:
            rows = np.flatnonzero(rows)
        out = self.blocks.gather(rows, self.which)
        if not rest:
            return out
        if rows.ndim == 0:
            return out[rest]
        if rows.ndim != 1:
            raise IndexError("LazyRows: rows and further indices need 1-D rows")
        return out[(np.arange(len(rows)),) + rest]

    def __array__(self, dtype=None, copy=None):
        out = self.blocks.gather(np.arange(self.blocks.num_rows), self.which)
        return out if dtype is None else out.astype(dtype)
