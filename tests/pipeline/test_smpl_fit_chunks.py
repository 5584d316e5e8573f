"""The chunked SMPL fit: the whole-sequence fit's accuracy, one body per track."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.body.model import load_body_model
from pipeline.data.scene import load_scene
from pipeline.evaluation.evaluate import ground_truth_slots, gt_per_frame, stage_metrics
from pipeline.fit.chunks import fit_in_chunks
from pipeline.fit.smpl import fit_sequence, target_slots
from tests.conftest import REPO

SCENE = REPO / "sample_data" / "shelf_synth"
F = 48


@pytest.fixture(scope="module")
def case():
    model = load_body_model()
    gt = load_scene(SCENE).gt
    keep = gt.frame < F
    tracks = np.full((4, F, 17, 3), np.nan)
    tracks[gt.person_id[keep], gt.frame[keep]] = gt.keypoints3d[keep]
    tracks += np.random.default_rng(0).normal(0, 10.0, tracks.shape)  # mm, like a triangulation
    tracks[3, :20] = np.nan  # a person who walks in during the second chunk
    return model, gt, tracks


def _mpjpe(gt, fit):
    """Fitted keypoints vs the true ones, where the fit has a body, mm."""
    kp_dense, _ = gt_per_frame(gt, ground_truth_slots(gt, "coco17")[0], F)
    return stage_metrics(target_slots(fit), kp_dense)[0]["mpjpe"]


@pytest.mark.slow
def test_chunks_fit_as_well_as_one_batch_with_one_body_per_track(case):
    model, gt, tracks = case
    whole, _ = fit_sequence(tracks, "coco17", model, progress=False)
    chunked, _ = fit_in_chunks(tracks, "coco17", model, chunk_frames=16, progress=False)
    np.testing.assert_array_equal(chunked.present, whole.present)
    assert np.isfinite(chunked.betas).all() and np.isfinite(chunked.keypoint_offsets).all()
    e_whole, e_chunk = _mpjpe(gt, whole), _mpjpe(gt, chunked)
    print(f"MPJPE whole {e_whole:.2f} mm, chunks of 16 {e_chunk:.2f} mm")
    assert e_chunk < e_whole + 1.0, (e_chunk, e_whole)
    # One body per track: every frame's joints are its pose on the track's one betas and
    # bone scales.
    assert np.isfinite(chunked.bone_scales).all()
    k, f = np.nonzero(chunked.present)
    with torch.no_grad():
        out = model(
            torch.as_tensor(chunked.pose_rotvecs[k, f].reshape(-1, 72), dtype=torch.float32),
            torch.as_tensor(chunked.betas[k], dtype=torch.float32),
            bone_scales=torch.as_tensor(chunked.bone_scales[k], dtype=torch.float32),
        )
    joints = 1000.0 * out.joints[:, :24].double().numpy() + chunked.transl[k, f][:, None]
    assert np.abs(joints - chunked.joints[k, f]).max() < 0.5  # mm


def test_chunk_arguments_are_checked(case):
    model, _, tracks = case
    with pytest.raises(ValueError, match="overlap"):
        fit_in_chunks(tracks, "coco17", model, chunk_frames=4, overlap=4, progress=False)


@pytest.mark.slow
def test_fit_bodies_fits_a_long_sequence_in_chunks(monkeypatch):
    """Past ``LONG_FIT_FRAMES`` the pipeline's fit is :func:`fit_in_chunks` (a 10,000-frame
    batch fit would not fit in memory); up to it, the batch fit as before."""
    import dataclasses as dc
    from pathlib import Path

    import pipeline.run.bodies as bodies_mod
    from pipeline.body.model import load_body_model, torch_body_model
    from pipeline.config import PipelineConfig
    from pipeline.data.scene import load_scene
    from pipeline.fit.smpl import fit_sequence
    from pipeline.run.frames import select_2d
    from pipeline.run.pipeline import run_stages

    scene = load_scene(Path(__file__).resolve().parents[2] / "sample_data" / "shelf_synth")
    config = dc.replace(PipelineConfig(), use_pose_prior=False)
    model = load_body_model()
    staged = run_stages(scene, config, select_2d(scene, config, None), restored=None,
                        progress=False)  # fmt: skip
    monkeypatch.setattr(bodies_mod, "LONG_FIT_FRAMES", 100)
    monkeypatch.setattr(bodies_mod, "LONG_FIT_CHUNK_FRAMES", 100)
    got = bodies_mod.fit_bodies(staged, config, model, progress=False)
    noise = bodies_mod.input_noise(staged)  # each track's smoothness follows its noise
    want, _ = fit_in_chunks(staged.track_smoothed, staged.joint_set, torch_body_model(model),
                            params=config.smpl_fit, chunk_frames=100, noise_mm=noise,
                            progress=False)  # fmt: skip
    whole, _ = fit_sequence(staged.track_smoothed, staged.joint_set, torch_body_model(model),
                            params=config.smpl_fit, noise_mm=noise, progress=False)  # fmt: skip
    assert got.smpl_vae is None and got.smpl.pose_rotvecs.shape == whole.pose_rotvecs.shape
    np.testing.assert_array_equal(got.smpl.pose_rotvecs, want.pose_rotvecs)
    np.testing.assert_array_equal(got.smpl.transl, want.transl)
    assert not np.array_equal(got.smpl.pose_rotvecs, whole.pose_rotvecs, equal_nan=True)
    ok = got.smpl.present  # the chunked fit is the same body within a few mm of the batch one
    assert np.nanmean(np.linalg.norm(got.smpl.joints - whole.joints, axis=-1)[ok]) < 5.0
    monkeypatch.setattr(bodies_mod, "LONG_FIT_FRAMES", 250)  # 250 frames: the batch fit
    again = bodies_mod.fit_bodies(staged, config, model, progress=False)
    np.testing.assert_array_equal(again.smpl.pose_rotvecs, whole.pose_rotvecs)
