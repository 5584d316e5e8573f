"""The Shelf / Campus protocol (pipeline/evaluation/protocol.py): hand-made poses with
known PCP, the truth files it reads, the head rule, and agreement with an independent
implementation of the rules written here from the data's README."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.io import savemat

from pipeline.core.files import SceneFormatError
from pipeline.data.joint_sets import get_joint_set
from pipeline.evaluation.protocol import (
    PROTOCOL_JOINTS,
    PROTOCOL_LIMBS,
    ProtocolTruth,
    estimates_by_frame,
    protocol_joints,
    read_protocol_gt,
    score_protocol,
)
from tests.conftest import SHELF_REAL

BODY25 = get_joint_set("body25")


def standing_pose(x: float = 0.0, y: float = 0.0) -> np.ndarray:
    """(15, 3) a person standing at (x, y) facing +y, z up, mm, protocol order."""
    p = np.array([
        [-100, 0, 0], [-100, 0, 450], [-100, 0, 900], [100, 0, 900], [100, 0, 450],
        [100, 0, 0], [-250, 0, 900], [-250, 0, 1150], [-200, 0, 1400], [200, 0, 1400],
        [250, 0, 1150], [250, 0, 900], [0, 0, 1500], [0, 60, 1750], [0, 0, 900],
    ], float)  # fmt: skip
    p[:, 0] *= -1  # facing +y with z up, the person's right is +x
    return p + [x, y, 0]


def truth_of(*rows: tuple[int, int, np.ndarray]) -> ProtocolTruth:
    return ProtocolTruth(
        frame=np.array([r[0] for r in rows]),
        actor=np.array([r[1] for r in rows]),
        joints=np.stack([r[2] for r in rows]),
    )


def test_perfect_and_threshold_limbs():
    gt = standing_pose()
    s = score_protocol({0: gt[None]}, truth_of((0, 0, gt)))
    assert s.average == 1.0 and s.per_actor == {0: 1.0} and s.mpjpe_mm == 0.0
    # move the right wrist so the lower arm's mean end error is exactly half its length
    a, b = PROTOCOL_LIMBS["right_lower_arm"]
    length = np.linalg.norm(gt[a] - gt[b])
    est = gt.copy()
    est[a, 0] += length  # err_a = length, err_b = 0: mean = length / 2 -> correct (<=)
    s = score_protocol({0: est[None]}, truth_of((0, 0, gt)))
    assert s.per_limb["right_lower_arm"] == 1.0
    est[a, 0] += 1.0  # 0.5 mm past the threshold: wrong
    s = score_protocol({0: est[None]}, truth_of((0, 0, gt)))
    assert s.per_limb["right_lower_arm"] == 0.0 and s.average == pytest.approx(0.9)
    assert s.wrong == ((0, 0, "right_lower_arm"),)


def test_missing_actor_and_actor_average():
    gt0, gt2 = standing_pose(), standing_pose(2000.0)
    truth = truth_of((0, 0, gt0), (0, 2, gt2), (1, 0, gt0), (1, 2, gt2), (0, 3, gt0))
    # frame 1 has only actor 0's estimate, which is the one nearest actor 2 there (2 m
    # away: every limb wrong); actor 3 is not one of the protocol's actors 1-3
    s = score_protocol({0: np.stack([gt0, gt2]), 1: gt0[None]}, truth)
    assert s.per_actor == {0: 1.0, 2: 0.5}
    assert s.average == pytest.approx(0.75)  # the mean over actors, not over limbs
    assert s.scored == 4 and s.missed == 0
    s = score_protocol({0: np.stack([gt0, gt2])}, truth)  # frame 1 without any estimate
    assert s.per_actor == {0: 0.5, 2: 0.5} and s.missed == 2
    # no estimate anywhere: every limb wrong, still scored
    s = score_protocol({}, truth)
    assert s.average == 0.0 and s.missed == 4 and np.isnan(s.mpjpe_mm)


def test_the_nearest_estimate_is_scored_even_a_ghost():
    gt = standing_pose()
    ghost = gt.copy()
    ghost[:, 2] += 80.0  # nearer than the real estimate, wrong head limb
    ghost[13] += [0, 0, 400.0]
    real = gt + [150.0, 0, 0]  # every joint 150 mm off: limbs below 300 mm long fail
    s = score_protocol({0: np.stack([real, ghost])}, truth_of((0, 0, gt)))
    assert s.per_limb["head"] == 0.0  # the ghost was chosen (mean error 80 + 400/14 mm)
    assert s.mpjpe_mm == pytest.approx((13 * 80.0 + 480.0) / 14)


def test_nan_joints_are_wrong_limbs():
    gt = standing_pose()
    est = gt.copy()
    est[PROTOCOL_JOINTS.index("left_wrist")] = np.nan
    s = score_protocol({0: est[None]}, truth_of((0, 0, gt)))
    assert s.per_limb["left_lower_arm"] == 0.0 and s.average == pytest.approx(0.9)


def test_head_rule_on_a_known_pose():
    """Bottom of the head halfway from mid-shoulders to mid-ears; top 125 mm along the
    face and 145 mm up (4D Association's rule), for a person facing +y."""
    kp = np.full((25, 3), np.nan)
    ix = BODY25.index
    kp[ix["right_shoulder"]] = [200, 0, 1400]  # facing +y: the right side is +x
    kp[ix["left_shoulder"]] = [-200, 0, 1400]
    kp[ix["right_ear"]] = [80, 0, 1600]
    kp[ix["left_ear"]] = [-80, 0, 1600]
    kp[ix["right_hip"]] = [100, 0, 900]
    kp[ix["left_hip"]] = [-100, 0, 900]
    for n in ("elbow", "wrist", "knee", "ankle"):
        kp[ix[f"right_{n}"]] = [300, 0, 500]
        kp[ix[f"left_{n}"]] = [-300, 0, 500]
    out = protocol_joints(kp, BODY25)
    np.testing.assert_allclose(out[PROTOCOL_JOINTS.index("head_bottom")], [0, 0, 1500])
    np.testing.assert_allclose(out[PROTOCOL_JOINTS.index("head_top")], [0, 125, 1645])
    np.testing.assert_allclose(out[PROTOCOL_JOINTS.index("pelvis")], [0, 0, 900])
    with pytest.raises(ValueError, match="lacks"):
        protocol_joints(np.zeros((24, 3)), get_joint_set("smpl24"))


def test_actors_gt_mat_in_the_datasets_layout(tmp_path):
    """actorsGT.mat: actor3D, one cell per actor, one per frame, 14 x 3 metres or empty."""
    poses = {(0, 0): standing_pose(), (0, 2): standing_pose(500.0), (1, 2): standing_pose(900.0)}
    actors = np.empty((1, 3), dtype=object)
    for a in range(3):
        cells = np.empty((3, 1), dtype=object)
        for f in range(3):
            p = poses.get((a, f))
            cells[f, 0] = np.zeros((0, 0)) if p is None else p[:14] / 1000.0
        actors[0, a] = cells
    savemat(tmp_path / "actorsGT.mat", {"actor3D": actors})
    t = read_protocol_gt(tmp_path / "actorsGT.mat")
    assert sorted(zip(t.actor.tolist(), t.frame.tolist(), strict=True)) == [(0, 0), (0, 2), (1, 2)]
    i = int(np.flatnonzero((t.actor == 1) & (t.frame == 2))[0])
    np.testing.assert_allclose(t.joints[i], standing_pose(900.0), atol=1e-6)  # pelvis: mid-hips


def test_bad_truth_files_name_the_field(tmp_path):
    np.savez(tmp_path / "a.npz", frame=np.zeros(2, int), person_id=np.zeros(2, int))
    with pytest.raises(SceneFormatError, match=r"a\.npz: field 'joints3d'"):
        read_protocol_gt(tmp_path / "a.npz")
    np.savez(tmp_path / "b.npz", frame=np.zeros(2), person_id=np.zeros(2, int),
             joints3d=np.zeros((2, 15, 3)))  # fmt: skip
    with pytest.raises(SceneFormatError, match=r"b\.npz: field 'frame'.*integers"):
        read_protocol_gt(tmp_path / "b.npz")
    savemat(tmp_path / "c.mat", {"other": np.zeros(3)})
    with pytest.raises(SceneFormatError, match=r"c\.mat: field 'actor3D'"):
        read_protocol_gt(tmp_path / "c.mat")
    with pytest.raises(SceneFormatError, match="not found"):
        read_protocol_gt(tmp_path / "none.npz")


def independent_pcp(estimates: dict[int, np.ndarray], truth: ProtocolTruth) -> dict[int, float]:
    """PCP per actor written from the data's README alone, a plain loop: for each
    annotated actor and frame the estimate nearest to it; a limb is correct when the mean
    of its two end points' errors is at most half the limb's true length."""
    limbs = [(0, 1), (1, 2), (3, 4), (4, 5), (6, 7), (7, 8), (9, 10), (10, 11), (12, 13), (12, 14)]
    correct: dict[int, list[int]] = {}
    for f, a, gt in zip(truth.frame, truth.actor, truth.joints, strict=True):
        if a > 2:
            continue
        best, best_err = None, np.inf
        for est in estimates.get(int(f), []):
            errs = [np.linalg.norm(est[j] - gt[j]) for j in range(14)]
            errs = [e for e in errs if np.isfinite(e)]
            if errs and np.mean(errs) < best_err:
                best, best_err = est, np.mean(errs)
        for s, e in limbs:
            ok = best is not None and (
                (np.linalg.norm(best[s] - gt[s]) + np.linalg.norm(best[e] - gt[e])) / 2
                <= 0.5 * np.linalg.norm(gt[s] - gt[e])
            )
            correct.setdefault(int(a), []).append(int(ok))
    return {a: float(np.mean(v)) for a, v in correct.items()}


def test_agrees_with_the_independent_rules_on_noisy_estimates():
    rng = np.random.default_rng(3)
    rows, estimates = [], {}
    for f in range(40):
        people = [standing_pose(0, 0), standing_pose(1500, 300), standing_pose(-900, 1200)]
        for a, p in enumerate(people):
            if rng.random() < 0.9:
                rows.append((f, a, p))
        est = [p + rng.normal(0, 60, p.shape) for p in people if rng.random() < 0.85]
        if est:
            estimates[f] = np.stack(est)
    truth = truth_of(*rows)
    ours = score_protocol(estimates, truth)
    ref = independent_pcp(estimates, truth)
    assert 0.3 < ours.average < 0.99  # the noise makes some limbs wrong, not all
    for a, v in ref.items():
        assert ours.per_actor[a] == pytest.approx(v, abs=1e-12)


@pytest.mark.slow
@pytest.mark.skipif(not SHELF_REAL.is_dir(), reason="../shared/data/shelf_real is absent")
def test_real_shelf_run_scored_by_the_protocol(tmp_path):
    """The real Shelf OpenPose detections, converted and run with default settings: the
    protocol agrees with the independent rules within 0.5 PCP, and the run clears a loose
    floor (the figures themselves are bench/bench_peer_shelf.py's)."""
    from mvviz.cli import main

    out = tmp_path / "shelf"
    assert main([
        "convert", "--from", "pose2sim", str(SHELF_REAL / "Calib.toml"),
        "--detections-from", "openpose", "--detections", str(SHELF_REAL / "openpose"),
        "-o", str(out),
    ]) == 0  # fmt: skip
    report = tmp_path / "pcp.json"
    assert main([
        "eval", str(out), "--protocol", "shelf", "--gt", str(SHELF_REAL / "gt_shelf15.npz"),
        "--json", str(report), "--no-sync",
    ]) == 0  # fmt: skip
    figures = json.loads(report.read_text())
    from pipeline.evaluation.evaluate import stage_tracks
    from pipeline.results.store import load_results

    results = load_results(out / ".mvviz" / "results.npz")
    truth = read_protocol_gt(SHELF_REAL / "gt_shelf15.npz")
    for name, tracks in stage_tracks(results).items():
        ref = independent_pcp(estimates_by_frame(tracks, BODY25), truth)
        ours = figures["stages"][name]
        assert abs(ours["average"] - np.mean(list(ref.values()))) <= 0.005, name
        assert ours["average"] > 0.90, name
    assert figures["tracks"]["long"] <= 4
