"""A results directory the viewer opens without reading it: one uncompressed ``.npy`` per
array, memory-mapped on open, beside a ``meta.json``.

``results.npz`` (compressed, one zip) has to be inflated whole before any frame shows: at
10,000 frames x 20 people x 31 cameras that is GBs. Here :func:`open_array_dir` maps
every array (``np.load(mmap_mode="r")``): indexing one frame's rows reads only the pages
that hold them, and the rows of a frame are contiguous (detections, person-frames and
edges are stored in frame order), so a frame change touches a few pages per array.

The directory is written whole into a temporary directory beside it and renamed into
place (:func:`pipeline.core.files.atomic_directory`): a failure mid-write leaves the previous
results as they were.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from pipeline.core.files import SceneFormatError, atomic_directory

META_FILE = "meta.json"


def write_array_dir(path: str | os.PathLike, meta: dict, arrays: dict[str, np.ndarray]) -> None:
    """``arrays`` as ``NAME.npy`` files and ``meta`` (plus the list of arrays) as
    ``meta.json`` in directory ``path``, replacing a previous one atomically."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise SceneFormatError(path, None, "exists and is not a results directory")
    bad = [k for k in arrays if not k.isidentifier()]
    if bad:
        raise ValueError(f"array names must be identifiers, got {bad[0]!r}")
    with atomic_directory(path, overwrite=True) as tmp:
        for name, a in arrays.items():
            np.save(tmp / f"{name}.npy", np.ascontiguousarray(a), allow_pickle=False)
        write_meta(tmp, meta, arrays)


def write_meta(path: str | os.PathLike, meta: dict, names) -> None:
    """``meta`` and the sorted array ``names`` as directory ``path``'s ``meta.json`` (the
    last file a writer puts in its temporary directory)."""
    full = {**meta, "arrays": sorted(names)}
    (Path(path) / META_FILE).write_text(json.dumps(full, indent=1) + "\n")


def read_meta(path: str | os.PathLike) -> dict:
    """The ``meta.json`` of results directory ``path`` (a clear error if it is not one)."""
    path = Path(path)
    meta_path = path / META_FILE
    if not meta_path.is_file():
        raise SceneFormatError(path, META_FILE, "missing: not an mvviz results directory")
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, ValueError) as exc:
        raise SceneFormatError(meta_path, None, f"not readable JSON ({exc})") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("arrays"), list):
        raise SceneFormatError(meta_path, "arrays", "expected a list of array names")
    return meta


def open_array_dir(path: str | os.PathLike) -> tuple[dict, dict[str, np.ndarray]]:
    """(meta, name -> read-only memory-mapped array: an ndarray view of an np.memmap)
    of results directory ``path``.
    Nothing but the ``.npy`` headers is read here."""
    path = Path(path)
    meta = read_meta(path)
    arrays: dict[str, np.ndarray] = {}
    for name in meta["arrays"]:
        p = path / f"{name}.npy"
        if not p.is_file():
            raise SceneFormatError(path, name, f"missing array file {p.name}")
        try:
            mapped = np.load(p, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError) as exc:  # a truncated file, a bad header
            raise SceneFormatError(p, None, f"not a readable .npy file ({exc})") from None
        # A plain ndarray view of the map: still paged in lazily, but without np.memmap's
        # Python-level __array_finalize__ / __array_wrap__ / __getitem__ on every slice and
        # result (~4.5 ms of a 31-camera frame change went there).
        arrays[name] = mapped.view(np.ndarray)
    return meta, arrays
