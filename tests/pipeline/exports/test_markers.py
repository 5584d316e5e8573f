"""TRC and C3D: round trips through our TRC reader and the c3d package's reader."""

from __future__ import annotations

import numpy as np

from pipeline.exports import export_results
from pipeline.exports.markers import marker_names, read_c3d_points
from pipeline.importers.trc import read_trc, trc_to_joint_set, trc_to_world_mm
from tests.pipeline.exports.conftest import GAPS


def test_marker_names_are_pose2sims_where_it_has_them():
    names = marker_names("coco17")
    assert names[:3] == ["Nose", "LEye", "REye"] and "RHip" in names and "LAnkle" in names
    assert marker_names("smpl24")[0] == "pelvis"  # no Pose2Sim names: ours


def test_trc_round_trip_every_stage_to_1e6_m(fitted_run, tmp_path):
    scene, res = fitted_run
    stages = {"raw": res.track_raw, "kalman": res.track_forward, "rts": res.track_smoothed,
              "smpl": res.smpl.keypoints, "smpl_vae": res.smpl_vae.keypoints}  # fmt: skip
    for stage, want in stages.items():
        [f] = export_results(res, "trc", tmp_path / f"{stage}.trc", fps=scene.fps, stage=stage)
        trc = read_trc(f.path)
        assert trc.units == "m" and trc.data_rate == scene.fps
        assert trc.num_frames == res.num_frames and trc.frame_numbers[0] == 1
        assert trc.marker_names[0] == "track0_Nose"
        back = trc_to_world_mm(trc).reshape(res.num_frames, 2, -1, 3).swapaxes(0, 1)
        np.testing.assert_allclose(back, want[:2], atol=1e-3, rtol=0)  # 1e-6 m
        # Y up: the TRC's Y is our z (height), metres
        heights = trc.points[..., 1]
        assert np.nanmin(heights) > -0.2 and np.nanmax(heights) < 2.2


def test_trc_per_track_reads_back_as_a_reference_in_our_joint_set(fitted_run, tmp_path):
    scene, res = fitted_run
    files = export_results(res, "trc", tmp_path / "p.trc", fps=scene.fps, per_track=True)
    for f in files:
        trc = read_trc(f.path)
        assert trc.marker_names[0] == "Nose"
        joints = trc_to_joint_set(trc, res.joint_set)
        k = f.tracks[0]
        np.testing.assert_allclose(joints, res.track_filtered[k], atol=1e-3, rtol=0)  # default


def test_trc_gaps_are_empty_cells(gappy_results, fitted_run, tmp_path):
    scene, _ = fitted_run
    res = gappy_results
    [f] = export_results(res, "trc", tmp_path / "g.trc", fps=scene.fps, stage="raw", track=1)
    assert "track-frames without a pose: empty cells" in f.notes[0]
    lines = f.path.read_text().splitlines()
    row = lines[6 + GAPS[2]].split("\t")  # header 5 lines + an empty one
    assert row[0] == str(GAPS[2] + 1) and all(c == "" for c in row[2:])
    back = trc_to_world_mm(read_trc(f.path))
    missing = ~np.isfinite(back).all(-1).any(-1)
    assert np.flatnonzero(missing).tolist() == list(GAPS)
    np.testing.assert_allclose(back, res.track_raw[1], atol=1e-3, rtol=0)


def test_c3d_round_trip_through_the_c3d_reader(gappy_results, fitted_run, tmp_path):
    scene, _ = fitted_run
    res = gappy_results
    [f] = export_results(res, "c3d", tmp_path / "all.c3d", fps=scene.fps, stage="smpl_vae")
    labels, pts, rate = read_c3d_points(f.path)
    assert rate == scene.fps and labels[0] == "track0_Nose" and len(labels) == 34
    want = np.concatenate([res.smpl_vae.keypoints[0], res.smpl_vae.keypoints[1]], axis=1)
    assert pts.shape == want.shape
    # float32 millimetres, z up: within 1e-3 mm; the gaps are invalid points
    np.testing.assert_allclose(pts, want, atol=1e-3, rtol=0)
    gone = ~np.isfinite(pts[:, 17:]).all(-1).any(-1)
    assert np.flatnonzero(gone).tolist() == list(GAPS)
    assert "residual -1" in f.notes[0]
