"""The lazy results layout (pipeline.results.array_dir through pipeline.results.store): a round trip
equal to the arrays written and to the .npz layout, memory-mapped on open, and an atomic
replace (a failure mid-write leaves the previous results whole)."""

from __future__ import annotations

import dataclasses
import json
import mmap

import numpy as np
import pytest

from pipeline.config import PipelineConfig
from pipeline.core.files import SceneFormatError
from pipeline.results.store import PipelineResults, load_results, save_results


def random_results(seed: int = 0, *, F: int = 12, V: int = 4, J: int = 17) -> PipelineResults:
    """Results of the right shapes and dtypes filled with random numbers (no pipeline run):
    3 people a frame, each seen by every view, 2 tracks."""
    rng = np.random.default_rng(seed)
    N, Q, E, K = F * V * 3, F * 3, F * 10, 2
    track = lambda *s: rng.normal(size=(K, F) + s)  # noqa: E731
    return PipelineResults(
        config=PipelineConfig(),
        joint_set="coco17",
        num_frames=F,
        num_views=V,
        det_joints2d=rng.normal(size=(N, J, 3)),
        det_restored=None,
        det_person=rng.integers(-1, Q, N),
        person_frame=np.repeat(np.arange(F), 3),
        person_joints=rng.normal(size=(Q, J, 3)),
        person_reproj=rng.normal(size=(Q, J, V)),
        person_used=rng.random((Q, J, V)) > 0.5,
        person_members=rng.integers(-1, N, (Q, V)),
        person_linkage=rng.random(Q),
        person_track=rng.integers(-1, K, Q),
        edge_a=rng.integers(0, N, E),
        edge_b=rng.integers(0, N, E),
        edge_affinity=rng.random(E),
        edge_distance=rng.random(E) * 100,
        track_raw=track(J, 3),
        track_forward=track(J, 3),
        track_smoothed=track(J, 3),
        track_prior=track(J, 3),
        track_innovation=track(J, 3),
        track_mahalanobis=track(J),
        track_rejected=track(J) > 1.0,
        track_resolved=track(J) > 1.5,
        track_contradicted=track(J) > 2.0,
        fit_floor=np.abs(rng.normal(size=(K, F))),
        cache_key=f"key{seed}",
        det_flipped=rng.random(N) > 0.9,
    )


ARRAYS = [
    f.name
    for f in dataclasses.fields(PipelineResults)
    if f.name not in {"config", "joint_set", "num_frames", "num_views", "cache_key", "smpl",
                      "smpl_vae", "det_restored"}
]  # fmt: skip


def is_mapped(arr: np.ndarray) -> bool:
    """Whether ``arr`` views a memory map (anywhere down its chain of bases)."""
    while arr is not None:
        if isinstance(arr, np.memmap | mmap.mmap):
            return True
        arr = getattr(arr, "base", None)
    return False


def assert_same(a: PipelineResults, b: PipelineResults) -> None:
    for name in ARRAYS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)
    assert (a.config, a.joint_set, a.num_frames, a.num_views, a.cache_key) == (
        b.config, b.joint_set, b.num_frames, b.num_views, b.cache_key,
    )  # fmt: skip


def test_directory_round_trip_is_memory_mapped_and_equals_npz(tmp_path):
    results = random_results()
    save_results(results, tmp_path / "results")
    save_results(results, tmp_path / "results.npz")
    lazy = load_results(tmp_path / "results")
    whole = load_results(tmp_path / "results.npz")
    assert_same(lazy, results)
    assert_same(whole, results)
    assert (tmp_path / "results").is_dir() and (tmp_path / "results.npz").is_file()
    for name in ("det_joints2d", "person_joints", "edge_a", "track_smoothed"):
        arr = getattr(lazy, name)
        assert is_mapped(arr), name  # mapped, not read
        assert type(arr) is np.ndarray, name  # a plain view: no np.memmap per-slice cost
    assert not is_mapped(whole.det_joints2d)
    with pytest.raises(ValueError):  # read-only: the viewer cannot change the file
        lazy.det_joints2d[0, 0, 0] = 1.0
    np.testing.assert_array_equal(lazy.people_in_frame(5), results.people_in_frame(5))


def test_a_failed_write_leaves_the_previous_results(tmp_path, monkeypatch):
    path = tmp_path / "results"
    old, new = random_results(0), random_results(1)
    save_results(old, path)
    written = []
    real_save = np.save

    def failing_save(file, arr, **kw):
        written.append(file)
        if len(written) == 5:  # some arrays of the new results are written already
            raise OSError("disk full")
        real_save(file, arr, **kw)

    monkeypatch.setattr(np, "save", failing_save)
    with pytest.raises(OSError, match="disk full"):
        save_results(new, path)
    monkeypatch.undo()
    assert len(written) == 5
    assert_same(load_results(path), old)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results"]  # no temporary left
    save_results(new, path)
    assert_same(load_results(path), new)


def test_bad_directories_name_the_file_and_field(tmp_path):
    path = tmp_path / "results"
    save_results(random_results(), path)
    (path / "person_joints.npy").write_bytes((path / "person_joints.npy").read_bytes()[:200])
    with pytest.raises(SceneFormatError, match="person_joints.npy"):
        load_results(path)
    (path / "person_joints.npy").unlink()
    with pytest.raises(SceneFormatError, match="person_joints"):
        load_results(path)
    save_results(random_results(), path)
    meta = json.loads((path / "meta.json").read_text())
    (path / "meta.json").write_text(json.dumps({**meta, "version": 1}))
    with pytest.raises(SceneFormatError, match="meta.version"):
        load_results(path)
    (path / "meta.json").unlink()
    with pytest.raises(SceneFormatError, match="meta.json"):
        load_results(path)
    with pytest.raises(SceneFormatError, match="not found"):
        load_results(tmp_path / "nothing")


@pytest.mark.slow
def test_a_long_scene_defaults_to_a_streamed_results_directory(tmp_path, monkeypatch):
    """default_results_path: one .npz for a short scene; for a long one (frames x cameras
    >= LONG_SCENE_VIEW_FRAMES), or where such a directory already is, the directory that
    run_or_load streams into and reopens memory-mapped (a 10,000-frame dome run in memory
    took ~11 GB)."""
    import shutil
    from pathlib import Path

    import pipeline.results.store as results_mod
    from pipeline.body.arrays import load_body_model_data
    from pipeline.data.scene import load_scene
    from pipeline.results.store import default_results_path
    from pipeline.run.pipeline import run_or_load

    src = Path(__file__).resolve().parents[2] / "sample_data" / "shelf_synth"
    shutil.copytree(src, tmp_path / "s", ignore=shutil.ignore_patterns(".mvviz"))
    scene = load_scene(tmp_path / "s")
    assert scene.num_frames * len(scene.rig) == 1250
    assert default_results_path(scene) == scene.root / ".mvviz" / "results.npz"
    monkeypatch.setattr(results_mod, "LONG_SCENE_VIEW_FRAMES", 1250)
    folder = default_results_path(scene)
    assert folder == scene.root / ".mvviz" / "results"
    config = dataclasses.replace(PipelineConfig(), fit_smpl=False)
    model = load_body_model_data(None)
    res, cached = run_or_load(scene, config, model, progress=False)
    assert not cached and folder.is_dir() and (folder / "meta.json").is_file()
    assert not (scene.root / ".mvviz" / "results.npz").exists()
    again, cached = run_or_load(scene, config, model, progress=False)
    assert cached and is_mapped(again.person_joints) and is_mapped(again.edge_a)
    np.testing.assert_array_equal(again.person_joints, res.person_joints)
    assert again.num_tracks == 4
    monkeypatch.setattr(results_mod, "LONG_SCENE_VIEW_FRAMES", 10**9)
    assert default_results_path(scene) == folder  # the directory there wins
