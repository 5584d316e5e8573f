"""The detection rows a synthesis makes, kept in memory or streamed to ``.npy`` columns.

A synthesis appends, per frame and view, the rows of the people a detector found and
of its ghosts. For a sample-sized scene the rows are kept as lists and joined at the
end; for a long one (10,000 frames x 31 cameras x 20 people: 4.6 M rows, ~5 GB of
keypoints and monocular SMPL columns) they go, every ``flush_rows`` rows, to the files
of a detections directory (:func:`pipeline.data.scene.open_detection_columns`), so the
synthesis holds a block of rows at a time whatever the scene's length. Both give the
same :class:`~pipeline.data.scene.Detections`, array for array.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.core.npy_stream import NpyRowAppender
from pipeline.data.scene import SMPL_FIELD_WIDTH, SMPL_FIELDS, Detections, open_detection_columns

COLUMNS = ("frame", "view", "keypoints", "gt_person_id", *SMPL_FIELDS)
FLUSH_ROWS = 1 << 16
"""Rows held before a streamed :class:`DetectionRows` appends them to its files (~80 MB
of keypoints and SMPL columns)."""


class DetectionRows:
    """Detection rows in the order they are appended.

    Args:
        num_joints: keypoints per row.
        directory: None keeps the rows in memory; a path (it must not exist) streams
            them to its ``COLUMN.npy`` files.
        flush_rows: rows held before they are appended to the files (None:
            :data:`FLUSH_ROWS`).
    """

    def __init__(
        self, num_joints: int, directory: Path | None = None, flush_rows: int | None = None
    ):
        self.num_joints = num_joints
        self.directory = None if directory is None else Path(directory)
        self.flush_rows = FLUSH_ROWS if flush_rows is None else flush_rows
        self._lists: dict[str, list[np.ndarray]] = {k: [] for k in COLUMNS}
        self._held = 0
        self._files: dict[str, NpyRowAppender] = {}
        if self.directory is not None:
            self.directory.mkdir()

    def append(
        self, frame: int, view: int, keypoints: np.ndarray, person: np.ndarray, smpl: dict
    ) -> None:
        """Rows of one view of one frame: keypoints (m, J, 3), person (m,) ground-truth
        ids (-1: a ghost), ``smpl`` the regressor's columns (``SMPL_FIELDS``), m rows each."""
        m = keypoints.shape[0]
        self._lists["frame"].append(np.full(m, frame))
        self._lists["view"].append(np.full(m, view))
        self._lists["keypoints"].append(keypoints)
        self._lists["gt_person_id"].append(np.asarray(person))
        for k in SMPL_FIELDS:
            self._lists[k].append(smpl[k])
        self._held += m
        if self.directory is not None and self._held >= self.flush_rows:
            self._flush()

    def _flush(self) -> None:
        if not self._held:
            return
        for k, parts in self._lists.items():
            block = np.concatenate(parts)
            if k not in self._files:
                self._files[k] = NpyRowAppender(self.directory / f"{k}.npy", block.dtype,
                                                block.shape[1:])  # fmt: skip
            self._files[k].append(block)
            parts.clear()
        self._held = 0

    def detections(self) -> Detections:
        """The rows as :class:`~pipeline.data.scene.Detections` (empty arrays for none); streamed,
        the files are closed and the columns memory-mapped."""
        if self.directory is None:
            arrays = {k: np.concatenate(v) for k, v in self._lists.items() if v}
        else:
            self._flush()
            for k, (dtype, shape) in self._empty_columns().items():
                if k not in self._files:  # no rows at all
                    self._files[k] = NpyRowAppender(self.directory / f"{k}.npy", dtype, shape)
            for f in self._files.values():
                f.close()
            arrays = open_detection_columns(self.directory)
        empty = self._empty_columns()
        cols = {
            k: arrays[k] if k in arrays else np.zeros((0, *s), d) for k, (d, s) in empty.items()
        }
        return Detections(**cols)

    def discard(self) -> None:
        """Close the files as they are (a failed synthesis; the caller removes them)."""
        for f in self._files.values():
            f.discard()

    def _empty_columns(self) -> dict[str, tuple[np.dtype, tuple[int, ...]]]:
        """Each column's dtype and row shape, as a synthesis makes them."""
        out = {k: (np.dtype(np.int64), ()) for k in ("frame", "view", "gt_person_id")}
        out["keypoints"] = (np.dtype(np.float64), (self.num_joints, 3))
        for k in SMPL_FIELDS:
            out[k] = (np.dtype(np.float64), (SMPL_FIELD_WIDTH[k],))
        return out
