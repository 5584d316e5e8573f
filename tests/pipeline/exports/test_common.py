"""Stage and track selection, gap handling and the dispatcher's refusals."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.core.palette import TRACK_PALETTE, track_rgb
from pipeline.exports import ExportError, available_stages, export_results, stages_for
from pipeline.exports.common import gap_note, hold_indices, per_track_paths, select_tracks


def test_hold_indices_hold_the_last_present_frame_and_the_first_before_it():
    present = np.array([0, 0, 1, 1, 0, 0, 1, 0], bool)
    assert hold_indices(present).tolist() == [2, 2, 2, 3, 3, 3, 6, 6]
    assert hold_indices(np.ones(3, bool)).tolist() == [0, 1, 2]


def test_gap_note_names_the_missing_runs():
    note = gap_note(np.array([1, 0, 0, 1, 0], bool), "held")
    assert note == "3 frames without a body (frames 1-2, 4): held"
    assert gap_note(np.ones(4, bool)) is None


def test_select_tracks():
    present = np.array([[1, 0], [0, 0], [0, 1]], bool)
    assert select_tracks(present, "all") == [0, 2]
    assert select_tracks(present, "2") == [2]
    with pytest.raises(ExportError, match=r"track 5 does not exist: the run has tracks 0..2"):
        select_tracks(present, 5)
    with pytest.raises(ExportError, match="track 1 has no frame"):
        select_tracks(present, 1)
    with pytest.raises(ExportError, match="expected 'all' or a track id"):
        select_tracks(present, "first")


def test_per_track_paths(tmp_path):
    assert per_track_paths(tmp_path / "a.bvh", [3]) == [tmp_path / "a.bvh"]
    assert per_track_paths(tmp_path / "a.bvh", [0, 2]) == [
        tmp_path / "a_track0.bvh", tmp_path / "a_track2.bvh"
    ]  # fmt: skip


def test_one_palette_for_viewer_rerun_and_exports():
    """Track k has one colour: the viewer's, the rerun recording's and the file exports'."""
    from mvviz.export.rerun.layout import track_color
    from mvviz.scene.geometry import track_color as viewer_color

    for k in range(2 * len(TRACK_PALETTE) + 1):
        assert tuple(int(c) for c in viewer_color(k)) == track_rgb(k) == track_color(k)
        assert track_color(k, raw=True) != track_color(k)
    assert len(set(TRACK_PALETTE)) == len(TRACK_PALETTE)


def test_a_stage_the_run_lacks_is_refused_naming_the_stages_it_has(fitted_run, tmp_path):
    scene, res = fitted_run
    assert available_stages(res) == ("raw", "kalman", "rts", "smpl", "smpl_vae")
    off = dataclasses.replace(res.config, fit_smpl=False)
    no_fit = dataclasses.replace(res, smpl=None, smpl_vae=None, config=off)
    assert stages_for(no_fit, "glb") == ()
    refused = r"no 'smpl' stage .*fit_smpl=false.*has: raw, kalman, rts"
    with pytest.raises(ExportError, match=refused):
        export_results(no_fit, "bvh", tmp_path / "x.bvh", fps=25, stage="smpl")
    with pytest.raises(ExportError, match="no 'smpl' stage"):
        export_results(no_fit, "glb", tmp_path / "x.glb", fps=25)  # default: the last fit
    no_vae = dataclasses.replace(res, smpl_vae=None)
    with pytest.raises(ExportError, match=r"no 'smpl_vae' stage \(the run has no VAE"):
        export_results(no_vae, "trc", tmp_path / "x.trc", fps=25, stage="smpl_vae")
    with pytest.raises(ExportError, match="bvh holds fitted bodies: --stage must be one of smpl"):
        export_results(res, "bvh", tmp_path / "x.bvh", fps=25, stage="rts")
    with pytest.raises(ExportError, match="unknown stage 'fit'"):
        export_results(res, "trc", tmp_path / "x.trc", fps=25, stage="fit")
    with pytest.raises(ExportError, match="unknown format 'fbx'"):
        export_results(res, "fbx", tmp_path / "x.fbx", fps=25)
    assert list(tmp_path.iterdir()) == []  # nothing written by a refused export


def test_file_names_and_defaults(fitted_run, tmp_path):
    scene, res = fitted_run
    trc = export_results(res, "trc", tmp_path / "all.trc", fps=scene.fps)
    assert [f.path.name for f in trc] == ["all.trc"] and trc[0].tracks == (0, 1)
    split = export_results(res, "c3d", tmp_path / "p.c3d", fps=scene.fps, per_track=True)
    assert [f.path.name for f in split] == ["p_track0.c3d", "p_track1.c3d"]
    one = export_results(res, "bvh", tmp_path / "one.bvh", fps=scene.fps, track=1)
    assert [f.path.name for f in one] == ["one.bvh"] and one[0].tracks == (1,)
    npz = export_results(res, "smpl-npz", tmp_path / "b.npz", fps=scene.fps)
    assert [f.path.name for f in npz] == ["b_track0.npz", "b_track1.npz"]
    assert np.load(tmp_path / "b_track0.npz")["stage"] == "smpl_vae"  # the last stage
    glb = export_results(res, "glb", tmp_path / "all.glb", fps=scene.fps, stage="smpl")
    assert glb[0].tracks == (0, 1)
    # atomic writes leave no temporaries behind
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_a_failed_write_keeps_the_old_file(fitted_run, tmp_path, monkeypatch):
    scene, res = fitted_run
    out = tmp_path / "x.glb"
    out.write_bytes(b"old")
    import pipeline.exports.gltf as gltf

    def boom(*a, **k):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(gltf, "glb_bytes", boom)
    with pytest.raises(RuntimeError):
        export_results(res, "glb", out, fps=scene.fps)
    assert out.read_bytes() == b"old"
