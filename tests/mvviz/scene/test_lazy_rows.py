"""Per-row arrays computed as indexed (mvviz.scene.lazy_rows), and the viewer on
memory-mapped results reading only the rows of the frame it shows: every other frame's
detection and person rows are poisoned (out-of-range indices, NaN, huge numbers) and the
frame's geometry and camera-panel overlay still equal those of the clean results."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mvviz.scene import lazy_rows
from mvviz.scene.geometry import LayerToggles, frame_geometry
from mvviz.scene.images import image_overlay
from mvviz.scene.lazy_rows import RowBlocks
from mvviz.state import ViewerState
from pipeline.results.store import load_results, save_results
from pipeline.run.frames import frame_rows

FRAME = 7


def test_row_blocks_gather_like_the_full_array_and_compute_only_what_is_indexed():
    full = np.random.default_rng(0).normal(size=(100, 5, 3))
    asked = []

    def compute(rows):
        asked.append(rows)
        return full[rows], full[rows, 0]

    blocks = RowBlocks(compute, 100, block_rows=16, cached_blocks=2)
    x, y = blocks.array(0), blocks.array(1)
    rows = np.array([40, 33, 47, 35])  # blocks 2 (32..47)
    np.testing.assert_array_equal(x[rows], full[rows])
    np.testing.assert_array_equal(x[rows, np.array([1, 2, 0, 4])], full[rows, [1, 2, 0, 4]])
    np.testing.assert_array_equal(y[rows], full[rows, 0])
    assert blocks.blocks_computed == 1 and [a.tolist() for a in asked] == [list(range(32, 48))]
    np.testing.assert_array_equal(x[np.array([99, 0])], full[[99, 0]])  # blocks 6 and 0
    np.testing.assert_array_equal(x[np.zeros(0, int)], full[:0])
    assert blocks.blocks_computed == 3
    x[rows]  # evicted (2 blocks kept): computed again
    assert blocks.blocks_computed == 4
    np.testing.assert_array_equal(np.asarray(x), full)
    with pytest.raises(IndexError):
        x[np.array([100])]


def poison_other_frames(path, rows_keep: np.ndarray, people_keep: np.ndarray) -> None:
    """Overwrite, in results directory ``path``, every detection row but ``rows_keep``
    and every person-frame but ``people_keep`` with values no frame could show (indices
    out of range: reading them raises)."""
    N_BAD = 10**9

    def rows_of(name, keep, value):
        a = np.load(path / f"{name}.npy", mmap_mode="r+")
        other = np.setdiff1d(np.arange(len(a)), keep)
        a[other] = value
        a.flush()

    rows_of("det_joints2d", rows_keep, np.nan)
    rows_of("det_person", rows_keep, N_BAD)
    for name, value in (("person_joints", 1e12), ("person_reproj", np.nan),
                        ("person_used", False), ("person_members", N_BAD),
                        ("person_linkage", np.nan)):  # fmt: skip
        rows_of(name, people_keep, value)


def geometry_arrays(x, prefix="") -> dict[str, np.ndarray]:
    """Every array inside a FrameGeometry (or an Overlay2D), by path."""
    out = {}
    if dataclasses.is_dataclass(x):
        for f in dataclasses.fields(x):
            out |= geometry_arrays(getattr(x, f.name), f"{prefix}.{f.name}")
    elif isinstance(x, list):
        for i, v in enumerate(x):
            out |= geometry_arrays(v, f"{prefix}[{i}]")
    elif isinstance(x, dict):
        for k, v in x.items():
            out |= geometry_arrays(v, f"{prefix}[{k}]")
    elif isinstance(x, np.ndarray):
        out[prefix] = x
    return out


def test_the_viewer_reads_only_the_frames_rows(viewer_scene, tmp_path, monkeypatch):
    scene, results, model = viewer_scene
    monkeypatch.setattr(lazy_rows, "BLOCK_ROWS", 1)  # a row computed is a row indexed
    rows = frame_rows(scene, results.config)[FRAME]
    people = results.people_in_frame(FRAME)
    assert len(rows) >= 4 and len(people) >= 2
    save_results(results, tmp_path / "r")
    poison_other_frames(tmp_path / "r", rows, people)
    poisoned = load_results(tmp_path / "r", model=model)
    other = np.setdiff1d(np.arange(len(poisoned.det_joints2d)), rows)
    assert np.isnan(poisoned.det_joints2d[other]).all()

    layers = LayerToggles(rays_selected_only=False, trails=False)
    views = {}
    for name, res in (("clean", results), ("poisoned", poisoned)):
        st = ViewerState.create(scene, res, model)
        assert st.data.det_rays.blocks.blocks_computed == 0  # nothing computed at start-up
        st.frame, st.layers = FRAME, layers
        geom = frame_geometry(st)
        overlays = [image_overlay(st.data, v, FRAME, layers) for v in range(len(scene.rig))]
        views[name] = geometry_arrays(geom) | geometry_arrays(overlays)
        assert 0 < st.data.det_rays.blocks.blocks_computed <= len(rows)
        assert st.data.det_track.blocks.blocks_computed <= len(rows)
    clean, bad = views["clean"], views["poisoned"]
    assert clean.keys() == bad.keys()
    assert sum(len(a) for a in clean.values()) > 100  # there is something drawn
    assert clean[".rays.segments"].shape[0] > 0
    for key in clean:
        np.testing.assert_array_equal(bad[key], clean[key], err_msg=key)
