"""pipeline.prior.sources (what the prior learns from, held-out mixes), the body-model
clips of pipeline.mocap.clips.clip_from_body, and the prior's in-distribution weight
(pipeline.fit.prior_correction.in_distribution)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.body import pose_limits
from pipeline.body.kinematics import rotvec_to_matrix
from pipeline.body.model import load_body_model
from pipeline.fit.prior import load_prior
from pipeline.fit.prior_correction import in_distribution
from pipeline.mocap.clips import clip_from_body
from pipeline.prior.heldout import check_activity_held_out, source_activities, training_frames
from pipeline.prior.sources import (
    BALANCING_POSES,
    DEMO_POSES,
    balancing_source,
    demo_source,
    library_source,
    mix_poses,
    sources_for,
)
from pipeline.synth.motion import LIBRARY_ACTIVITIES, sample_pose_library


def test_balancing_source_is_the_trials_fitted_poses_with_its_terms():
    src = balancing_source()
    assert src.poses.shape == (100, 72) and np.isfinite(src.poses).all()
    rec = src.record
    assert rec["activities"] == ["balance"] and "BSD-3-Clause" in rec["licence"]
    assert rec["source_frames"] == 100 and rec["fps"] == 60.0
    # a fitted real person: mostly inside the joint limits, and not a rest pose
    assert pose_limits.violations_per_1000(src.poses.reshape(-1, 24, 3)) < 100
    assert np.abs(src.poses[:, 3:66]).max() > 0.3
    assert training_frames([rec]) == {(BALANCING_POSES.name, i) for i in range(100)}


def test_demo_source_is_two_real_people_one_standing_upright():
    src = demo_source()
    assert src.poses.shape == (200, 72) and np.isfinite(src.poses).all() and src.real
    rec = src.record
    assert rec["activities"] == ["stand", "walk"] and "BSD-3-Clause" in rec["licence"]
    assert rec["tracks"] == [0, 1] and rec["source_frames"] == 200
    assert training_frames([rec]) == {(DEMO_POSES.name, i) for i in range(200)}
    with np.load(DEMO_POSES) as z:
        track, trans = z["track"], z["trans"]
        assert z["betas"].shape == (2, 10) and (np.bincount(track) == 100).all()
    poses = src.poses.reshape(-1, 24, 3)
    knee = np.degrees(
        np.linalg.norm(poses[:, [pose_limits.J["left_knee"], pose_limits.J["right_knee"]]], axis=-1)
    )
    speed = [
        np.median(np.linalg.norm(np.diff(trans[track == k, :2], axis=0), axis=1)) * 60
        for k in (0, 1)
    ]
    # measured: person 0 stands almost still (0.20 m/s median, knees bent 16-19 deg on
    # average), person 1 walks across (0.58 m/s)
    assert speed[0] < 0.3 < 0.45 < speed[1], speed
    assert np.median(knee[track == 0]) < 25.0
    # step I on real 2D (no prior): 130 and 160 per 1,000 bodies outside a joint limit, measured
    assert pose_limits.violations_per_1000(poses) < 200


def test_library_without_an_activity_and_the_mix_records():
    lib = library_source(num_poses=2000, kinds=("reach", "crouch"))
    assert lib.record["activities"] == ["reach", "crouch"] and not lib.real
    # the default library is unchanged; an activity's poses are that activity's
    np.testing.assert_array_equal(
        sample_pose_library(500, seed=2), sample_pose_library(500, seed=2, kinds=LIBRARY_ACTIVITIES)
    )
    knee = pose_limits.J["left_knee"]
    bend = {
        k: np.linalg.norm(sample_pose_library(500, kinds=(k,)).reshape(-1, 24, 3)[:, knee], axis=-1)
        for k in ("walk", "crouch")
    }
    assert np.median(bend["crouch"]) > 1.2 > 0.6 > np.median(bend["walk"])
    poses, records = mix_poses([lib, balancing_source()], min_real_poses=1000)
    assert [r["repeat"] for r in records] == [1, 10]
    assert len(poses) == len(lib.poses) + 1000
    np.testing.assert_array_equal(poses[-100:], balancing_source().poses)


def test_sources_for_a_split_hold_no_held_out_activity():
    sources = sources_for(exclude_sources=("cmu",), exclude_activities=("wave",), num_poses=1000)
    records = [s.record for s in sources]
    assert [s.name for s in sources] == ["library", "balancing", "demo"]
    check_activity_held_out(records, "wave")  # passes
    with pytest.raises(ValueError, match="balance"):
        check_activity_held_out(records, "balance")
    no_bal = sources_for(exclude_sources=("cmu",), exclude_activities=("balance",), num_poses=1000)
    assert [s.name for s in no_bal] == ["library", "demo"]
    no_walk = sources_for(exclude_sources=("cmu",), exclude_activities=("walk",), num_poses=1000)
    assert [s.name for s in no_walk] == ["library", "balancing"]  # the demo shows walking
    assert source_activities({"activity": "start, hop, stop"}) == {"hop"}
    with pytest.raises(ValueError, match="unknown sources"):
        sources_for(exclude_sources=("amass",))


def test_clip_from_body_stands_on_the_floor_and_keeps_the_model_joints():
    model = load_body_model()
    poses = sample_pose_library(20, seed=4).reshape(-1, 24, 3)
    poses[:, 0] = [np.pi / 2, 0.0, 0.0]  # canonical y up -> world z up
    transl = np.zeros((20, 3))
    transl[:, 2] = 500.0 + 30.0 * np.sin(np.arange(20))  # floating, bobbing
    clip = clip_from_body("c", poses, np.zeros(10), transl, model, fps=25.0, activity="x",
                          licence="generated")  # fmt: skip
    with torch.no_grad():
        out = model(torch.as_tensor(poses, dtype=torch.float32), torch.zeros(20, 10))
    joints = out.joints.double().numpy() * 1000.0 + transl[:, None]
    shift = clip.smpl24 - joints  # one vertical shift for the whole clip
    np.testing.assert_allclose(shift[..., :2], 0.0, atol=1e-3)
    np.testing.assert_allclose(shift[..., 2], shift[0, 0, 2], atol=1e-3)
    verts = out.vertices.double().numpy() * 1000.0 + transl[:, None] + shift[:, :1]
    assert abs(verts[..., 2].min()) < 1e-3 and abs(shift[0, 0, 2]) > 100.0
    assert clip.coco17.shape == (20, 17, 3) and np.isfinite(clip.coco17).all()
    assert clip.joint_names[0] == "pelvis" and clip.info()["source_frames"] == 20


def test_in_distribution_trusts_known_poses_and_not_strange_ones():
    prior = load_prior()
    known = sample_pose_library(300, seed=99).reshape(-1, 24, 3)
    rng = np.random.default_rng(0)
    strange = known.copy()
    strange[:, 1:22] += rng.normal(0, 0.6, strange[:, 1:22].shape)  # 35 deg per axis
    out = []
    for poses in (known, strange):
        R = torch.as_tensor(rotvec_to_matrix(poses), dtype=torch.float32)
        with torch.no_grad():
            out.append(in_distribution(prior, R, prior.encode_rotmats(R[:, 1:]), 1.0).numpy())
    assert np.median(out[0]) == 1.0 and (out[0] > 0.5).mean() > 0.95
    assert np.median(out[1]) < 0.2 and (out[1] <= 1.0).all() and (out[1] > 0).all()
    R = torch.eye(3).repeat(4, 24, 1, 1)
    assert (in_distribution(prior, R, torch.zeros(4, prior.latent), 0.0) == 1).all()
