"""The stages streamed into a results directory (pipeline/run/streamed.py) write the
arrays the in-memory stages give, bit for bit, and read a lazily loaded scene."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

import pipeline.run.streamed as streamed
from pipeline.config import PipelineConfig
from pipeline.core.files import SceneFormatError
from pipeline.core.npy_stream import is_mapped
from pipeline.data.scene import load_scene, write_scene
from pipeline.results.store import EDGE_FIELDS, save_results, scene_fingerprint
from pipeline.run.chunked import run_stages_chunked
from pipeline.run.frames import select_2d

SCENES = Path(__file__).resolve().parents[2] / "sample_data"


def assert_same_directories(a: Path, b: Path) -> None:
    meta_a, meta_b = (json.loads((p / "meta.json").read_text()) for p in (a, b))
    assert meta_a == meta_b
    for name in meta_a["arrays"]:
        x, y = np.load(a / f"{name}.npy"), np.load(b / f"{name}.npy")
        assert x.dtype == y.dtype and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)


def degenerate(scene):
    """The sample with frames 20-39 empty, camera 2 gone in frames 50-119, one detection
    of frame 60 all NaN and one person's rows dropped for 30 frames."""
    det = scene.detections
    keep = ~((det.frame >= 20) & (det.frame < 40))
    keep &= ~((det.view == 2) & (det.frame >= 50) & (det.frame < 120))
    if det.gt_person_id is not None:
        keep &= ~((det.gt_person_id == 1) & (det.frame >= 150) & (det.frame < 180))
    det = det.take(keep)
    kp = det.keypoints.copy()
    row = int(np.flatnonzero(det.frame == 60)[0])
    kp[row, :, :2], kp[row, :, 2] = np.nan, 0.0
    return dataclasses.replace(scene, detections=dataclasses.replace(det, keypoints=kp))


@pytest.mark.slow
@pytest.mark.parametrize("case", ["shelf_synth", "shelf_synth_noisy", "degenerate"])
def test_streamed_directory_equals_the_in_memory_results_saved(tmp_path, monkeypatch, case):
    scene = load_scene(SCENES / ("shelf_synth" if case == "degenerate" else case))
    if case == "degenerate":
        scene = degenerate(scene)
    config = PipelineConfig()
    j2d = select_2d(scene, config, None)
    want = run_stages_chunked(scene, config, j2d, restored=None, key="k", progress=False)
    save_results(want, tmp_path / "want")
    # chunks of 7 frames and the filter one track at a time: every seam is crossed
    monkeypatch.setattr(streamed, "FILTER_BLOCK_STEPS", 1)
    got = streamed.run_stages_streamed(
        scene, config, j2d, tmp_path / "got", restored=None, key="k", chunk_frames=7,
        progress=False,
    )  # fmt: skip
    assert_same_directories(tmp_path / "want", tmp_path / "got")
    assert want.num_tracks >= 4 and len(want.edge_a) > 1000 and got.num_tracks == want.num_tracks
    assert is_mapped(got.track_smoothed) and is_mapped(got.det_joints2d)
    if case == "degenerate":
        assert not np.isin(np.arange(20, 40), got.person_frame).any()
    else:
        assert got.det_flipped.sum() >= 1  # a flipped row is written over the copied input
        flipped = np.flatnonzero(got.det_flipped)
        assert not np.array_equal(got.det_joints2d[flipped], j2d[flipped])


@pytest.mark.slow
def test_lean_streamed_run_has_empty_edges_and_a_cancelled_run_keeps_the_old(tmp_path):
    scene = load_scene(SCENES / "shelf_synth")
    config = PipelineConfig()
    j2d = select_2d(scene, config, None)
    lean = streamed.run_stages_streamed(
        scene, config, j2d, tmp_path / "r", restored=None, keep_edges=False, progress=False
    )
    for k in EDGE_FIELDS:
        assert len(getattr(lean, k)) == 0 and getattr(lean, k).dtype.kind in "if", k
    before = sorted(p.name for p in (tmp_path / "r").iterdir())
    calls = iter(range(10**6))
    gone = streamed.run_stages_streamed(
        scene, config, j2d, tmp_path / "r", restored=None, progress=False,
        cancelled=lambda: next(calls) >= 30,
    )  # fmt: skip
    assert gone is None
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r"]  # no temporary left behind
    with pytest.raises(ValueError, match="chunk_frames"):
        streamed.run_stages_streamed(
            scene, config, j2d, tmp_path / "x", restored=None, chunk_frames=0, progress=False
        )


def _as_directory_scene(src: Path, out: Path):
    s = load_scene(src)
    write_scene(
        out, name=s.name, fps=s.fps, num_frames=s.num_frames, joint_set=s.joint_set, rig=s.rig,
        detections=s.detections, detections_file="detections",
    )  # fmt: skip
    return s


@pytest.mark.slow
def test_a_scene_with_a_detections_directory_is_read_lazily_and_runs_the_same(tmp_path):
    npz = _as_directory_scene(SCENES / "shelf_synth", tmp_path / "scene")
    lazy = load_scene(tmp_path / "scene")
    assert (tmp_path / "scene" / "detections" / "keypoints.npy").is_file()
    assert is_mapped(lazy.detections.keypoints) and lazy.detections.keypoints.dtype == np.float64
    np.testing.assert_array_equal(lazy.detections.keypoints, npz.detections.keypoints)
    np.testing.assert_array_equal(lazy.detections.frame, npz.detections.frame)
    config = PipelineConfig()
    j2d = select_2d(lazy, config, None)
    assert is_mapped(j2d)  # the stages read the mapped rows, not a copy
    got = streamed.run_stages_streamed(
        lazy, config, j2d, tmp_path / "got", restored=None, key="k", progress=False
    )
    save_results(
        run_stages_chunked(npz, config, npz.detections.keypoints, restored=None, key="k",
                           progress=False),
        tmp_path / "want",
    )  # fmt: skip
    assert_same_directories(tmp_path / "want", tmp_path / "got")
    assert got.num_tracks >= 4
    # the cache key follows the directory's contents
    key = scene_fingerprint(lazy)
    kp = np.load(tmp_path / "scene" / "detections" / "keypoints.npy")
    kp[0, 0, 0] += 1.0
    np.save(tmp_path / "scene" / "detections" / "keypoints.npy", kp)
    assert scene_fingerprint(load_scene(tmp_path / "scene")) != key


def test_a_bad_detections_directory_names_the_file_and_field(tmp_path):
    _as_directory_scene(SCENES / "shelf_synth", tmp_path / "scene")
    path = tmp_path / "scene" / "detections" / "keypoints.npy"
    kp = np.load(path)
    kp[70_000 % len(kp), 3, 2] = -0.5
    np.save(path, kp)
    with pytest.raises(SceneFormatError, match=r"detections.*keypoints\[\.\.\., 2\].*>= 0"):
        load_scene(tmp_path / "scene")
    path.write_bytes(b"\x93NUMPY truncated")
    with pytest.raises(SceneFormatError, match=r"keypoints.npy.*not a readable .npy file"):
        load_scene(tmp_path / "scene")
    path.unlink()
    with pytest.raises(SceneFormatError, match=r"keypoints.*missing"):
        load_scene(tmp_path / "scene")


@pytest.mark.slow
def test_run_or_load_into_a_directory_streams_and_equals_the_saved_run(tmp_path):
    """``mvviz run --out DIR``: the streamed stages plus the SMPL fits write the files
    that saving the in-memory run writes, and a second call loads them (cached)."""
    from pipeline.body.model import load_body_model
    from pipeline.run.pipeline import run_or_load, run_pipeline

    scene = load_scene(SCENES / "shelf_synth")
    config = PipelineConfig()
    model = load_body_model()
    got, cached = run_or_load(scene, config, model, out=tmp_path / "got", progress=False)
    assert not cached and got.smpl is not None and got.smpl_vae is not None
    assert is_mapped(got.track_smoothed) and is_mapped(got.smpl.transl)
    save_results(run_pipeline(scene, config, model, progress=False), tmp_path / "want")
    assert_same_directories(tmp_path / "want", tmp_path / "got")
    again, cached = run_or_load(scene, config, model, out=tmp_path / "got", progress=False)
    assert cached and again.cache_key == got.cache_key
    np.testing.assert_array_equal(again.smpl.pose_rotvecs, got.smpl.pose_rotvecs)
