"""Metrics: hand-computed small cases, NaN / empty inputs, and a few laws."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.data.joint_sets import SMPL24, coco17_smpl24_pairs
from pipeline.evaluation.metrics import (
    PCP_LIMB_GROUPS,
    PCP_LIMBS,
    SMPL24_COCO_JOINTS,
    acceleration,
    acceleration_error,
    association_scores,
    id_switch_events,
    id_switches,
    jitter,
    joint_errors,
    limb_correct,
    match_people,
    match_sequence,
    mpjpe,
    mpjpe_matrix,
    pck,
    pcp,
    pcp_per_person,
    per_view_joint_reprojection,
    pose_metrics,
)

NAN = float("nan")


def body(seed: int = 0, offset=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(24, 3) a plausible SMPL-24 skeleton in mm: joints 100-400 mm from their parents."""
    rng = np.random.default_rng(seed)
    j = np.zeros((24, 3))
    for c, p in enumerate(SMPL24.parents):
        if p >= 0:
            d = rng.normal(size=3)
            j[c] = j[p] + d / np.linalg.norm(d) * rng.uniform(100, 400)
    return j + np.asarray(offset)


# --- joint errors, MPJPE, PCK ------------------------------------------------------


def test_joint_errors_nan_where_either_missing():
    gt = np.zeros((2, 3))
    pred = np.array([[3.0, 4.0, 0.0], [NAN, 0.0, 0.0]])
    np.testing.assert_array_equal(joint_errors(pred, gt), [5.0, NAN])
    with pytest.raises(ValueError, match="shape"):
        joint_errors(np.zeros((2, 3)), np.zeros((3, 3)))


def test_mpjpe_of_constant_offset_is_the_offset():
    gt = body()
    assert mpjpe(gt + [6.0, 8.0, 0.0], gt) == pytest.approx(10.0)
    assert mpjpe(np.stack([gt, gt]) + [0.0, 0.0, 10.0], np.stack([gt, gt])) == pytest.approx(10.0)


def test_mpjpe_skips_nan_and_restricts_to_subset():
    gt = np.zeros((24, 3))
    pred = np.zeros((24, 3))
    pred[:, 0] = 10.0
    pred[SMPL24_COCO_JOINTS, 0] = 30.0
    pred[SMPL24.index["head"]] = NAN
    assert mpjpe(pred, gt, joints=SMPL24_COCO_JOINTS) == pytest.approx(30.0)
    # 12 joints at 30, 11 finite at 10 (head missing).
    assert mpjpe(pred, gt) == pytest.approx((12 * 30 + 11 * 10) / 23)
    assert np.isnan(mpjpe(np.full((24, 3), NAN), gt))
    assert np.isnan(mpjpe(np.zeros((0, 24, 3)), np.zeros((0, 24, 3))))


def test_coco_subset_is_joint_sets_mapping():
    np.testing.assert_array_equal(SMPL24_COCO_JOINTS, coco17_smpl24_pairs()[1])
    assert len(SMPL24_COCO_JOINTS) == 12


def test_pck():
    assert pck(np.array([100.0, 200.0])) == 0.5
    assert pck(np.array([160.0])) == 0.0  # strictly below the threshold
    assert pck(np.array([100.0, NAN, 200.0, 50.0]), threshold=150.0) == pytest.approx(2 / 3)
    assert np.isnan(pck(np.array([])))
    assert np.isnan(pck(np.array([NAN, NAN])))


# --- matching ----------------------------------------------------------------------


def test_match_people_recovers_a_swapped_pair():
    a, b = body(0), body(1, offset=(2000.0, 0.0, 0.0))
    gt = np.stack([a, b])
    pred = np.stack([b + 5.0, a - 5.0])
    assert match_people(pred, gt) == [(0, 1), (1, 0)]
    np.testing.assert_allclose(mpjpe_matrix(pred, gt)[[0, 1], [1, 0]], np.sqrt(75.0))


def test_match_people_rejects_pairs_above_the_gate():
    gt = np.stack([body(0), body(1, offset=(3000.0, 0.0, 0.0))])
    pred = np.stack([body(0) + [0.0, 0.0, 400.0], body(1, offset=(3000.0, 0.0, 600.0))])
    assert match_people(pred, gt, max_mpjpe=500.0) == [(0, 0)]
    assert match_people(pred, gt, max_mpjpe=600.0) == [(0, 0), (1, 1)]  # <= gate matches
    assert match_people(pred, gt, max_mpjpe=100.0) == []


def test_match_people_prefers_more_matches_over_lower_cost():
    # pred 0 is 100 mm from gt 0 and 450 from gt 1; pred 1 only reaches gt 0 (400 mm).
    # Cheapest single pair (p0, g0) would leave p1 unmatched; two matches win.
    g = np.zeros((2, 24, 3))
    g[1] += [0.0, 0.0, 550.0]
    p = np.zeros((2, 24, 3))
    p[0] += [0.0, 0.0, 100.0]
    p[1] += [0.0, 0.0, -400.0]
    assert match_people(p, g, max_mpjpe=500.0) == [(0, 1), (1, 0)]


def test_match_people_nan_and_empty():
    gt = np.stack([body(0)])
    ghost = np.full((24, 3), NAN)
    assert match_people(np.stack([ghost, body(0) + 1.0]), gt) == [(1, 0)]
    partial = body(0) + 1.0
    partial[:20] = NAN  # still matches on the 4 joints it has
    assert match_people(partial[None], gt) == [(0, 0)]
    assert match_people(np.zeros((0, 24, 3)), gt) == []
    assert match_people(gt, np.zeros((0, 24, 3))) == []
    assert match_people(ghost[None], gt) == []


def test_match_sequence_and_pose_metrics():
    a, b = body(0), body(1, offset=(2000.0, 0.0, 0.0))
    absent = np.full((24, 3), NAN)
    # Frame 0: both GT, both predicted (10 mm off), swapped order + a far false positive.
    # Frame 1: GT b absent; one prediction for a.  Frame 2: GT a missed entirely.
    gts = [np.stack([a, b]), np.stack([a, absent]), np.stack([a, b])]
    far = body(2, offset=(9000.0, 0.0, 0.0))
    preds = [
        np.stack([b + [10.0, 0, 0], a + [10.0, 0, 0], far]),
        (a + [0, 10.0, 0])[None],
        (b + [0, 0, 10.0])[None],
    ]
    m = match_sequence(preds, gts)
    np.testing.assert_array_equal(m.frame, [0, 0, 1, 2, 2])
    np.testing.assert_array_equal(m.gt_index, [0, 1, 0, 0, 1])
    np.testing.assert_array_equal(m.pred_index, [1, 0, 0, -1, 0])
    assert np.isnan(m.pred[3]).all()
    s = pose_metrics(m)
    assert (s["num_gt"], s["num_pred"], s["num_matched"]) == (5, 5, 4)
    assert s["recall"] == pytest.approx(4 / 5)
    assert s["precision"] == pytest.approx(4 / 5)
    assert s["mpjpe"] == pytest.approx(10.0)
    assert s["mpjpe_coco"] == pytest.approx(10.0)
    assert s["pck"] == 1.0 and s["pck_coco"] == 1.0
    # Person a: frames 0, 1 perfect, frame 2 missed -> 2/3; person b: all correct.
    assert s["pcp"] == pytest.approx((2 / 3 + 1.0) / 2)
    assert pose_metrics(m, pcp_persons=[0])["pcp"] == pytest.approx(2 / 3)


def test_match_sequence_empty():
    m = match_sequence([], [])
    assert m.gt.shape == (0, 0, 3) and m.num_pred == 0
    s = pose_metrics(m)
    assert s["num_gt"] == 0 and np.isnan(s["recall"]) and np.isnan(s["mpjpe"])
    assert np.isnan(s["pcp"])
    m = match_sequence([np.zeros((0, 24, 3))], [np.zeros((0, 24, 3))])
    assert len(m.frame) == 0
    s = pose_metrics(match_sequence([np.zeros((0, 24, 3))], [body()[None]]))
    assert s["recall"] == 0.0 and np.isnan(s["precision"]) and s["pcp"] == 0.0


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(1, 4),
    seed=st.integers(0, 10_000),
    perm_seed=st.integers(0, 10_000),
    noise=st.floats(0.0, 80.0),
)
def test_matched_mpjpe_is_invariant_to_people_order(n, seed, perm_seed, noise):
    rng = np.random.default_rng(seed)
    gt = np.stack([body(seed + i, offset=(1500.0 * i, 0.0, 0.0)) for i in range(n)])
    pred = gt + rng.normal(0.0, noise, gt.shape)
    perm = np.random.default_rng(perm_seed).permutation(n)

    def matched_mpjpe(p):
        pairs = match_people(p, gt)
        pi, gi = zip(*pairs, strict=True)
        return mpjpe(p[list(pi)], gt[list(gi)]), len(pairs)

    e0, k0 = matched_mpjpe(pred)
    e1, k1 = matched_mpjpe(pred[perm])
    assert k0 == k1 == n
    assert e1 == pytest.approx(e0, rel=1e-12, abs=1e-9)
    assert {(int(perm[p]), g) for p, g in match_people(pred[perm], gt)} == set(
        match_people(pred, gt)
    )


# --- PCP -----------------------------------------------------------------------------


def test_pcp_limbs_are_the_ten_shelf_limbs():
    assert len(PCP_LIMBS) == 10
    assert sorted(n for g in PCP_LIMB_GROUPS.values() for n in g) == sorted(PCP_LIMBS)
    assert PCP_LIMBS["torso"] == (SMPL24.index["pelvis"], SMPL24.index["neck"])


def test_pcp_of_a_perfect_prediction_is_one():
    gt = np.stack([body(0), body(1)])
    r = pcp(gt.copy(), gt)
    assert r["average"] == 1.0
    assert all(v == 1.0 for v in r["limbs"].values())
    assert all(v == 1.0 for v in r["groups"].values())


def _straight_arm() -> np.ndarray:
    """A body whose left lower arm (elbow -> wrist) is exactly 400 mm along x."""
    gt = body(0)
    e, w = SMPL24.index["left_elbow"], SMPL24.index["left_wrist"]
    gt[w] = gt[e] + [400.0, 0.0, 0.0]
    return gt


def test_pcp_mean_endpoint_rule_and_its_boundary():
    gt = _straight_arm()
    w = SMPL24.index["left_wrist"]
    e = SMPL24.index["left_elbow"]
    limb = list(PCP_LIMBS).index("left_lower_arm")

    def lower_arm_ok(pred):
        return limb_correct(pred, gt)[limb]

    pred = gt.copy()
    pred[w] += [0.0, 240.0, 0.0]  # one endpoint off 0.6 x length: mean 0.3 L <= 0.5 L
    assert lower_arm_ok(pred) == 1.0
    pred = gt.copy()
    pred[w] += [0.0, 400.0, 0.0]  # one endpoint off 1.0 x length: mean exactly 0.5 L
    assert lower_arm_ok(pred) == 1.0
    pred[w] += [0.0, 1e-6, 0.0]  # just past the boundary
    assert lower_arm_ok(pred) == 0.0
    pred = gt.copy()
    pred[[e, w]] += [0.0, 240.0, 0.0]  # both endpoints 0.6 L off: mean 0.6 L
    assert lower_arm_ok(pred) == 0.0
    # The wrist ends no other PCP limb: moving it past the boundary fails only this one.
    pred = gt.copy()
    pred[w] += [0.0, 400.0 + 1e-6, 0.0]
    r = pcp(pred[None], gt[None])
    assert r["limbs"]["left_lower_arm"] == 0.0
    assert r["groups"]["lower_arms"] == 0.5
    assert r["average"] == pytest.approx(0.9)


def test_pcp_nan_prediction_is_wrong_nan_gt_is_not_scored():
    gt = body(0)
    r = pcp(np.full((1, 24, 3), NAN), gt[None])
    assert r["average"] == 0.0
    gt_missing = gt.copy()
    gt_missing[SMPL24.index["head"]] = NAN
    c = limb_correct(gt.copy(), gt_missing)
    assert np.isnan(c[list(PCP_LIMBS).index("head")])
    assert np.nansum(c) == 9
    r = pcp(gt[None].copy(), gt_missing[None])
    assert np.isnan(r["limbs"]["head"]) and r["average"] == 1.0
    assert np.isnan(pcp(np.zeros((0, 24, 3)), np.zeros((0, 24, 3)))["average"])
    with pytest.raises(ValueError, match="SMPL-24"):
        limb_correct(np.zeros((17, 3)), np.zeros((17, 3)))


def test_pcp_per_person_counts_unmatched_as_all_wrong():
    a, b = body(0), body(1)
    gt = np.stack([a, a, a, a, b])
    pred = gt.copy()
    pred[3] = NAN  # person 0 missed in one of its four frames
    r = pcp_per_person(pred, gt, np.array([0, 0, 0, 0, 1]))
    assert r["per_person"] == {0: 0.75, 1: 1.0}
    assert r["average"] == pytest.approx(0.875)
    assert r["per_person_groups"][0]["torso"] == 0.75
    assert pcp_per_person(pred, gt, np.array([0, 0, 0, 0, 1]), persons=[0, 2])[
        "average"
    ] == pytest.approx(0.75)  # absent person 2 ignored


# --- temporal --------------------------------------------------------------------------


def test_acceleration_is_second_difference():
    x = np.array([0.0, 1.0, 4.0, 9.0, 16.0])[:, None] * np.ones(3)  # t^2: a = 2
    np.testing.assert_allclose(acceleration(x), 2.0)
    assert acceleration(x[:2]).shape == (0, 3)


def test_acceleration_error_offset_and_alternating_noise():
    t = np.arange(20.0)
    gt = np.stack([np.stack([t * 30.0, np.sin(t) * 50.0, t**2], -1)] * 5, axis=1)  # (20, 5, 3)
    assert acceleration_error(gt + [7.0, -3.0, 11.0], gt) == pytest.approx(0.0, abs=1e-9)
    d = 4.0
    sign = (-1.0) ** t
    pred = gt + d * sign[:, None, None] * np.array([0.6, 0.8, 0.0])
    assert acceleration_error(pred, gt) == pytest.approx(4 * d)
    assert jitter(gt + [1.0, 2.0, 3.0]) == pytest.approx(jitter(gt))
    line = t[:, None, None] * np.ones((20, 2, 3))
    assert jitter(line) == pytest.approx(0.0)


def test_acceleration_error_nan_and_short():
    t = np.arange(6.0)
    gt = np.zeros((6, 1, 3))
    pred = gt + 2.0 * ((-1.0) ** t)[:, None, None] * np.array([1.0, 0, 0])
    pred[2] = NAN  # removes the accelerations centred at t = 1, 2, 3
    assert acceleration_error(pred, gt) == pytest.approx(8.0)  # t = 4 remains
    pred[4] = NAN
    assert np.isnan(acceleration_error(pred, gt))
    assert np.isnan(acceleration_error(gt[:2], gt[:2]))
    assert np.isnan(jitter(np.zeros((0, 24, 3))))


# --- association ---------------------------------------------------------------------


def test_association_scores_one_wrong_assignment():
    # One frame, 4 views: person 0 seen in views 0-2, person 1 in view 3 and a false
    # positive (gt -1). The association put view 2's detection of person 0 into
    # person 1's cluster and left the false positive unassigned.
    gt = np.array([0, 0, 0, 1, 1, -1])
    cl = np.array([5, 5, 7, 7, 7, -1])
    r = association_scores(cl, gt, np.zeros(6, int))
    # true pairs: {0,1},{0,2},{1,2} (person 0) + {3,4} (person 1) = 4
    # pred pairs: {0,1} (cluster 5) + {2,3},{2,4},{3,4} (cluster 7) = 4
    # correct: {0,1}, {3,4} = 2
    assert (r["true_pairs"], r["pred_pairs"], r["correct_pairs"]) == (4, 4, 2)
    assert r["precision"] == 0.5 and r["recall"] == 0.5 and r["f1"] == 0.5
    assert r["false_positives_assigned"] == 0 and r["detections_unassigned"] == 1


def test_association_scores_pairs_stay_within_frames():
    # Same ids in two frames never pair across frames.
    r = association_scores(np.array([0, 0]), np.array([0, 0]), np.array([0, 1]))
    assert (r["true_pairs"], r["pred_pairs"]) == (0, 0)
    assert r["precision"] == 1.0 and r["recall"] == 1.0  # 0 / 0 defined as 1
    r = association_scores(np.array([3, 3, 3]), np.array([0, 0, -1]), np.zeros(3, int))
    assert r["precision"] == pytest.approx(1 / 3) and r["recall"] == 1.0
    assert r["false_positives_assigned"] == 1
    r = association_scores(np.array([], int), np.array([], int), np.array([], int))
    assert r["precision"] == 1.0 and r["true_pairs"] == 0
    with pytest.raises(ValueError, match="length"):
        association_scores(np.zeros(2, int), np.zeros(3, int), np.zeros(2, int))


# --- identity switches -----------------------------------------------------------------


def test_id_switches_counts_a_single_swap():
    frames = np.array([0, 0, 1, 1, 2, 2])
    gt = np.array([0, 1, 0, 1, 0, 1])
    tracks = np.array([10, 11, 10, 11, 11, 10])  # swap at frame 2
    assert id_switches(frames, gt, tracks) == 2  # each of the two GT persons switches once
    events = id_switch_events(frames, gt, tracks)
    assert events == [(2, 0, 10, 11), (2, 1, 11, 10)]
    # One person alone changing track once: exactly 1.
    assert id_switches(np.array([0, 1, 2]), np.array([0, 0, 0]), np.array([4, 4, 9])) == 1


def test_id_switches_memory_survives_gaps():
    # Person 0 tracked as 3, unmatched in frames 2-4, comes back as 3: no switch.
    frames = np.array([0, 1, 5, 6])
    assert id_switches(frames, np.zeros(4, int), np.array([3, 3, 3, 3])) == 0
    # ... comes back as 8 after the gap: a switch (the memory was not reset).
    assert id_switch_events(frames, np.zeros(4, int), np.array([3, 3, 8, 8])) == [(5, 0, 3, 8)]
    # Input order does not matter.
    assert id_switches(frames[::-1], np.zeros(4, int), np.array([8, 8, 3, 3])) == 1
    # Switching back and forth counts every change.
    assert id_switches(np.arange(3), np.zeros(3, int), np.array([1, 2, 1])) == 2


def test_id_switches_empty_and_invalid():
    e = np.array([], int)
    assert id_switches(e, e, e) == 0
    with pytest.raises(ValueError, match="twice"):
        id_switches(np.array([0, 0]), np.array([1, 1]), np.array([2, 3]))


# --- reprojection ----------------------------------------------------------------------


def test_per_view_joint_reprojection():
    e = np.full((2, 1, 2, 3), NAN)  # frames, people, joints, views
    e[0, 0, 0, 0], e[1, 0, 0, 0] = 1.0, 5.0
    e[0, 0, 1, 0] = 2.0
    e[:, 0, 1, 1] = [4.0, 6.0]
    r = per_view_joint_reprojection(e)
    np.testing.assert_array_equal(r["mean"], [[3.0, 2.0], [NAN, 5.0], [NAN, NAN]])
    np.testing.assert_array_equal(r["median"], [[3.0, 2.0], [NAN, 5.0], [NAN, NAN]])
    np.testing.assert_array_equal(r["count"], [[2, 1], [0, 2], [0, 0]])
    np.testing.assert_allclose(r["view_mean"], [8 / 3, 5.0, NAN])
    np.testing.assert_allclose(r["view_median"], [2.0, 5.0, NAN])
    empty = per_view_joint_reprojection(np.zeros((0, 0, 24, 4)))
    assert empty["mean"].shape == (4, 24) and np.isnan(empty["mean"]).all()
    with pytest.raises(ValueError, match="num_views"):
        per_view_joint_reprojection(np.zeros((3, 4)))
