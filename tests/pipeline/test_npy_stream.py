"""``.npy`` files written a piece at a time (pipeline/core/npy_stream.py)."""

from __future__ import annotations

import os

import numpy as np
import pytest

from pipeline.core.npy_stream import (
    NpyRowAppender,
    _mapping,
    is_mapped,
    mapped_arrays,
    open_npy_for_writing,
    release_pages,
)

PAGE = os.sysconf("SC_PAGE_SIZE")


def rss_bytes() -> int:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * PAGE


@pytest.mark.parametrize(
    ("dtype", "row_shape"),
    [(np.float64, (17, 3)), (np.int32, ()), (bool, (17, 31)), (np.float32, (5,))],
)
def test_appended_rows_read_back_as_their_concatenation(tmp_path, dtype, row_shape):
    rng = np.random.default_rng(0)
    chunks = [(rng.normal(size=(n, *row_shape)) * 100).astype(dtype) for n in (3, 0, 1, 250, 7)]
    w = NpyRowAppender(tmp_path / "a.npy", dtype, row_shape)
    for c in chunks:
        w.append(c)
    w.close()
    w.close()  # a second close does nothing
    got = np.load(tmp_path / "a.npy")
    want = np.concatenate(chunks)
    assert got.dtype == np.dtype(dtype) and got.shape == want.shape == (261, *row_shape)
    np.testing.assert_array_equal(got, want)
    mapped = np.load(tmp_path / "a.npy", mmap_mode="r")
    np.testing.assert_array_equal(mapped[250:], want[250:])


def test_an_unclosed_file_reads_as_no_rows_and_wrong_rows_are_refused(tmp_path):
    w = NpyRowAppender(tmp_path / "a.npy", np.float64, (4,))
    w.append(np.ones((10, 4)))
    w._fh.flush()
    assert np.load(tmp_path / "a.npy").shape == (0, 4)  # never read as complete
    with pytest.raises(ValueError, match=r"a.npy: rows of shape \(4,\) expected, got \(3,\)"):
        w.append(np.ones((2, 3)))
    w.close()
    assert np.load(tmp_path / "a.npy").shape == (10, 4)
    empty = NpyRowAppender(tmp_path / "e.npy", np.int64, (2,))
    empty.close()
    got = np.load(tmp_path / "e.npy")
    assert got.shape == (0, 2) and got.dtype == np.int64


def test_a_written_map_holds_its_values_and_releasing_drops_its_pages(tmp_path):
    n = 32 << 20  # 256 MB of float64 would be slow here; 32 M bytes is enough to see
    out = open_npy_for_writing(tmp_path / "m.npy", np.uint8, (n,), fill=7)
    assert is_mapped(out) and is_mapped(out[5:10]) and not is_mapped(np.zeros(3))
    before = rss_bytes()
    out[:] = 3  # every page of the map resident...
    touched = rss_bytes() - before
    assert release_pages(out)
    after = rss_bytes() - before
    assert touched > n // 2 and after < n // 8, (touched, after)  # ...then handed back
    out[-1] = 9
    out.flush()
    del out
    got = np.load(tmp_path / "m.npy", mmap_mode="r")
    assert got.shape == (n,) and got[0] == 3 and got[n // 2] == 3 and got[-1] == 9
    assert not release_pages(np.zeros(4))  # not mapped: nothing to release


def test_filled_map_has_the_fill_everywhere(tmp_path):
    out = open_npy_for_writing(tmp_path / "f.npy", np.float64, (1000, 17, 3), fill=np.nan)
    out.flush()
    assert np.isnan(np.load(tmp_path / "f.npy")).all()


def test_mapped_arrays_finds_each_file_map_once_however_nested(tmp_path):
    """Views of one map count once; plain arrays, scalars and strings are not maps; a
    map inside a dataclass inside a dict inside a tuple is found."""
    import dataclasses

    paths = []
    for name in ("a", "b"):
        np.save(tmp_path / f"{name}.npy", np.arange(12.0).reshape(4, 3))
        paths.append(tmp_path / f"{name}.npy")
    a, b = (np.load(p, mmap_mode="r") for p in paths)

    @dataclasses.dataclass(frozen=True)
    class Holder:
        x: np.ndarray
        y: np.ndarray
        name: str = "holder"

    nested = ({"h": Holder(x=a[1:], y=np.zeros(3))}, [b, b[::2]], 3.0)
    found = mapped_arrays(nested, a)
    assert len(found) == 2
    assert {id(_mapping(f)) for f in found} == {id(_mapping(a)), id(_mapping(b))}
    assert mapped_arrays(np.zeros(3), {"k": [1, 2]}, "text") == []
    # too deep to look: a map four containers down is not searched past depth
    assert mapped_arrays([[[[[a]]]]], depth=2) == []
