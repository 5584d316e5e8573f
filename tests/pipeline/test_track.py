"""Tracking: stable IDs through close passes and gaps, births and deaths."""

from __future__ import annotations

import numpy as np

from pipeline.core.assignment import gated_assignment
from pipeline.stages.track import TrackingParams, match_to_tracks, track_people


def _walkers(num_frames: int, sep_mm: float, seed: int = 0) -> np.ndarray:
    """Two 17-joint 'people' walking towards each other and passing at ``sep_mm``."""
    rng = np.random.default_rng(seed)
    body = rng.normal(0, 200, (17, 3))
    t = np.arange(num_frames)
    a = np.stack([-3000 + 50 * t, np.full_like(t, -sep_mm / 2), np.zeros_like(t)], -1)
    b = np.stack([3000 - 50 * t, np.full_like(t, sep_mm / 2), np.zeros_like(t)], -1)
    return np.stack([a[:, None] + body, b[:, None] + body[::-1]], 1).astype(float)  # (F, 2, 17, 3)


def _rows(people: np.ndarray, noise: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    F, P = people.shape[:2]
    frames = np.repeat(np.arange(F), P)
    joints = people.reshape(F * P, -1, 3) + rng.normal(0, noise, (F * P, people.shape[2], 3))
    truth = np.tile(np.arange(P), F)
    order = rng.permutation(F * P)
    return frames[order], joints[order], truth[order]


def test_close_pass_keeps_identities():
    people = _walkers(120, sep_mm=650)
    frames, joints, truth = _rows(people, noise=20)
    tr = track_people(frames, joints, 120)
    assert tr.num_tracks == 2
    for p in range(2):
        assert len(set(tr.track_of[truth == p].tolist())) == 1


def test_gap_is_bridged_and_long_gap_starts_a_new_track():
    people = _walkers(60, sep_mm=2000)
    frames, joints, truth = _rows(people, noise=10)
    hidden = (truth == 0) & (frames >= 20) & (frames < 28)  # 8 frames unseen
    tr = track_people(frames[~hidden], joints[~hidden], 60, TrackingParams(max_gap=12))
    assert tr.num_tracks == 2
    assert len(set(tr.track_of[truth[~hidden] == 0].tolist())) == 1
    track0 = tr.track_of[truth[~hidden] == 0][0]
    assert np.isnan(tr.joints[track0, 22]).all() and np.isfinite(tr.joints[track0, 30]).all()
    hidden = (truth == 0) & (frames >= 20) & (frames < 40)  # 20 frames: the track dies
    tr = track_people(frames[~hidden], joints[~hidden], 60, TrackingParams(max_gap=12))
    assert tr.num_tracks == 3
    assert sorted(tr.first_frame.tolist()) == [0, 0, 40]


def test_people_with_too_few_joints_are_not_tracked():
    people = _walkers(10, sep_mm=2000)
    frames, joints, truth = _rows(people, noise=5)
    joints[truth == 1, 3:] = np.nan  # person 1: 3 joints only
    tr = track_people(frames, joints, 10, TrackingParams(min_joints=6))
    assert tr.num_tracks == 1 and (tr.track_of[truth == 1] == -1).all()


def test_empty_input():
    tr = track_people(np.zeros(0, int), np.zeros((0, 17, 3)), 5)
    assert tr.num_tracks == 0 and tr.joints.shape == (0, 5, 17, 3)


def test_match_to_tracks_gates_and_assigns_one_to_one():
    ref = np.zeros((3, 5, 3))
    ref[1] += 1000.0
    ref[2] = np.nan  # a track absent in this frame
    people = np.stack([ref[1] + 10.0, ref[0] + 5.0, ref[0] + 3000.0])
    assert match_to_tracks(people, ref, 400.0).tolist() == [1, 0, -1]


def test_gated_assignment_maximises_matches_before_cost():
    # the cheapest single pair (0, 0) would leave row 1 unmatched: two matches win
    cost = np.array([[1.0, 5.0], [2.0, np.inf]])
    rows, cols = gated_assignment(cost)
    assert rows.tolist() == [0, 1] and cols.tolist() == [1, 0]
    rows, cols = gated_assignment(cost, cost < 3.0)  # (0, 1) not allowed: one match
    assert len(rows) == 1 and cost[rows[0], cols[0]] < 3.0
    assert [len(x) for x in gated_assignment(np.full((2, 3), np.inf))] == [0, 0]


def test_a_ghost_seen_in_fewer_than_min_hits_frames_is_no_track():
    people = _walkers(30, sep_mm=2000)
    frames, joints, truth = _rows(people, noise=10)
    rng = np.random.default_rng(1)
    ghost = rng.normal(0, 200, (2, 17, 3)) + [0.0, 5000.0, 0.0]  # far from both walkers
    frames = np.concatenate([frames, [7, 8]])  # one ghost seen twice, beside the walkers
    joints = np.concatenate([joints, ghost])
    tr = track_people(frames, joints, 30, TrackingParams(min_hits=3))
    assert tr.num_tracks == 2 and (tr.track_of[-2:] == -1).all()
    assert sorted(set(tr.track_of[:-2].tolist())) == [0, 1]
    assert np.isfinite(tr.joints).all(-1).any(-1).sum(-1).tolist() == [30, 30]
    kept = track_people(frames, joints, 30, TrackingParams(min_hits=2))
    assert kept.num_tracks == 3 and kept.track_of[-1] == kept.track_of[-2] == 2
