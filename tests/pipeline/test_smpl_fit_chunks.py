"""The chunked SMPL fit: the whole-sequence fit's accuracy, one body per track."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.body_model import load_body_model
from pipeline.evaluate import ground_truth_slots, gt_per_frame, stage_metrics
from pipeline.scene import load_scene
from pipeline.smpl_fit import fit_sequence, target_slots
from pipeline.smpl_fit_chunks import fit_in_chunks
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


def test_chunks_fit_as_well_as_one_batch_with_one_body_per_track(case):
    model, gt, tracks = case
    whole, _ = fit_sequence(tracks, "coco17", model, progress=False)
    chunked, _ = fit_in_chunks(tracks, "coco17", model, chunk_frames=16, progress=False)
    np.testing.assert_array_equal(chunked.present, whole.present)
    assert np.isfinite(chunked.betas).all() and np.isfinite(chunked.keypoint_offsets).all()
    e_whole, e_chunk = _mpjpe(gt, whole), _mpjpe(gt, chunked)
    print(f"MPJPE whole {e_whole:.2f} mm, chunks of 16 {e_chunk:.2f} mm")
    assert e_chunk < e_whole + 1.0, (e_chunk, e_whole)
    # One body per track: every frame's joints are its pose on the track's one betas.
    k, f = np.nonzero(chunked.present)
    with torch.no_grad():
        out = model(
            torch.as_tensor(chunked.pose_rotvecs[k, f].reshape(-1, 72), dtype=torch.float32),
            torch.as_tensor(chunked.betas[k], dtype=torch.float32),
        )
    joints = 1000.0 * out.joints[:, :24].double().numpy() + chunked.transl[k, f][:, None]
    assert np.abs(joints - chunked.joints[k, f]).max() < 0.5  # mm


def test_chunk_arguments_are_checked(case):
    model, _, tracks = case
    with pytest.raises(ValueError, match="overlap"):
        fit_in_chunks(tracks, "coco17", model, chunk_frames=4, overlap=4, progress=False)
