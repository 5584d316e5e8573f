"""AMASS-style npz: our body model on the file's poses, betas, bone scales and trans gives
the fitted vertices back within 1e-4 m."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.exports import export_results
from pipeline.exports.smpl_npz import write_smpl_npz_track
from tests.pipeline.exports.conftest import synthetic_fit


def _vertices(model, z):
    n = len(z["poses"])
    with torch.no_grad():
        out = model(
            torch.as_tensor(z["poses"].reshape(-1, 24, 3)).float(),
            torch.as_tensor(np.tile(z["betas"], (n, 1))).float(),
            bone_scales=torch.as_tensor(np.tile(z["bone_scales"], (n, 1))).float(),
        )
    return out.vertices.double().numpy() + z["trans"][:, None]  # metres


@pytest.mark.slow
def test_amass_npz_round_trip_of_the_vertices(fitted_run, model, tmp_path):
    scene, res = fitted_run
    fit = res.smpl_vae
    for f in export_results(res, "smpl-npz", tmp_path / "p.npz", fps=scene.fps):
        [k] = f.tracks
        z = np.load(f.path)
        assert z["poses"].shape == (res.num_frames, 72) and z["trans"].shape == (res.num_frames, 3)
        assert z["betas"].shape == (10,) and str(z["gender"]) == "neutral"
        assert float(z["mocap_framerate"]) == scene.fps
        assert str(z["body_model_sha256"]) == model.fingerprint
        assert str(z["surface_model_type"]) == "smpl-format:open_body_24.npz"
        assert "z up" in str(z["world_convention"])
        verts = _vertices(model, z)
        for fr in range(res.num_frames):
            want = fit.vertices(k, fr) / 1000.0
            assert np.abs(verts[fr] - want).max() < 1e-4
        np.testing.assert_allclose(z["joints"], fit.joints[k] / 1000.0, atol=1e-9)


def test_amass_npz_of_large_rotations(model, tmp_path):
    fit = synthetic_fit(model, num_frames=4, scale=2.5, seed=1)
    write_smpl_npz_track(tmp_path / "t.npz", fit, 1, fps=60.0)
    z = np.load(tmp_path / "t.npz")
    verts = _vertices(model, z)
    for fr in range(4):
        assert np.abs(verts[fr] - fit.vertices(1, fr) / 1000.0).max() < 1e-4


def test_amass_npz_keeps_the_tracks_span_and_marks_held_rows(gappy_results, fitted_run, tmp_path):
    scene, _ = fitted_run
    fit = gappy_results.smpl_vae
    [f] = export_results(gappy_results, "smpl-npz", tmp_path / "g.npz", fps=scene.fps, track=1)
    z = np.load(f.path)
    assert int(z["frame_offset"]) == 2 and len(z["poses"]) == 9  # frames 2..10
    assert z["present"].tolist() == [1, 1, 1, 0, 0, 1, 1, 1, 1]
    np.testing.assert_array_equal(z["poses"][3], z["poses"][2])  # frame 5 holds frame 4
    np.testing.assert_allclose(z["trans"][0], fit.transl[1, 2] / 1000.0)
    assert np.isfinite(z["poses"]).all() and np.isfinite(z["trans"]).all()
    assert any("scene frames 2-10" in n for n in f.notes)
