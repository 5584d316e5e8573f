"""The proportion check: joints that contradict their track's bones are re-solved from
the views that fit, or flagged and skipped by the Kalman filter."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.config import PipelineConfig
from pipeline.data.joint_sets import get_joint_set
from pipeline.stages.kalman import KalmanParams, kalman_filter
from pipeline.stages.proportions import (
    PersonEvidence,
    ProportionParams,
    check_proportions,
    skeleton_tree,
    track_bone_medians,
)
from pipeline.stages.triangulate import triangulate_people
from tests.pipeline.helpers import shelf_rig, standing_people

SMPL = get_joint_set("smpl24")
BONES = np.array(SMPL.bones)
ELBOW, WRIST = SMPL.index["right_elbow"], SMPL.index["right_wrist"]
SHOULDER = SMPL.index["right_shoulder"]
F = 30


def test_skeleton_tree_roots_at_the_joint_of_most_bones():
    # a star around joint 1 with a chain 1-3-4: root 1, 4 reached through 3
    parent, order = skeleton_tree(np.array([[0, 1], [1, 2], [1, 3], [3, 4]]), 6)
    assert order[0] == 1 and parent[1] == -1
    assert parent.tolist() == [1, -1, 1, 1, 3, -1]  # joint 5: no bone reaches it
    assert order.index(4) > order.index(3)


def test_track_medians_need_enough_frames():
    joints = np.zeros((12, 2, 3))
    joints[:, 1, 0] = 300.0
    joints[:10, 1, 0] = 310.0  # track 0: 10 frames at 310 (median), track 1: 2 frames
    track = np.array([0] * 10 + [1] * 2)
    med = track_bone_medians(joints, track, np.array([[0, 1]]), 2, min_frames=5)
    assert med[0, 0] == pytest.approx(310.0) and np.isnan(med[1, 0])


class Capture:
    """One person walking 30 frames past the real Shelf rig, seen by its 5 cameras;
    the 2D of chosen views of the right elbow replaced by a point ``off_mm`` further
    along the upper arm (a longer arm by that much: another person's elbow)."""

    def __init__(self):
        self.rig = shelf_rig()
        base = standing_people(np.array([[0.0, 0.0]]), np.array([0.3]), seed=3)[0]
        self.truth = np.stack([base + [8.0 * f, 0.0, 0.0] for f in range(F)])  # (F, J, 3)
        V, J = len(self.rig), self.truth.shape[1]
        uv = self.rig.project(self.truth)  # (V, F, J, 2)
        self.obs = np.concatenate([uv, np.ones((V, F, J, 1))], -1).transpose(1, 0, 2, 3)
        self.used = np.ones((F, J, V), bool)
        self.joints = self.truth.copy()

    def wrong_elbow(self, f: int, wrong_views, seen_views, off_mm: float = 220.0) -> None:
        """In frame ``f`` the elbow is seen by ``seen_views`` only, ``wrong_views`` of them
        showing the displaced point; the triangulation kept the views that show it."""
        t = self.truth[f]
        arm = (t[ELBOW] - t[SHOULDER]) / np.linalg.norm(t[ELBOW] - t[SHOULDER])
        wrong = t[ELBOW] + off_mm * arm
        for v in range(len(self.rig)):
            if v not in seen_views:
                self.obs[f, v, ELBOW] = (np.nan, np.nan, 0.0)
            elif v in wrong_views:
                self.obs[f, v, ELBOW, :2] = self.rig[v].project(wrong[None])[0]
        kept = list(wrong_views) if len(wrong_views) >= 2 else list(seen_views)
        self.used[f, ELBOW] = np.isin(np.arange(len(self.rig)), kept)
        kp = np.where(self.used[f, ELBOW][:, None], self.obs[f, :, ELBOW], np.nan)
        kp = np.broadcast_to(kp[None, :, None], (1, len(self.rig), 1, 3)).copy()
        self.joints[f, ELBOW] = triangulate_people(
            self.rig, kp, outlier_threshold_px=np.inf
        ).points[0, 0]

    def evidence(self) -> PersonEvidence:
        V = len(self.rig)
        return PersonEvidence(
            rig=self.rig,
            joints2d=self.obs.reshape(F * V, -1, 3),
            members=np.arange(F * V).reshape(F, V),
            used=self.used,
        )

    def check(self, params: ProportionParams | None = None):
        return check_proportions(self.joints, np.zeros(F, int), 1, BONES, self.evidence(), params)


def test_wrong_view_pair_is_re_solved_from_the_pair_that_fits():
    cap = Capture()
    # views 0 and 1 see the elbow where it is, views 2 and 3 show another place, and
    # the triangulation kept views 2-3 (as on real Shelf: the right views dropped)
    for f in (10, 11, 12):
        cap.wrong_elbow(f, wrong_views=[2, 3], seen_views=[0, 1, 2, 3])
    before = np.linalg.norm(cap.joints[10:13, ELBOW] - cap.truth[10:13, ELBOW], axis=-1)
    assert before.min() > 150
    out = cap.check()
    assert out.resolved[10:13, ELBOW].all()
    assert not out.contradicted.any()
    after = np.linalg.norm(out.joints[10:13, ELBOW] - cap.truth[10:13, ELBOW], axis=-1)
    assert after.max() < 2.0
    # every other joint and frame untouched
    out.resolved[10:13, ELBOW] = False
    assert not out.resolved.any()
    np.testing.assert_array_equal(np.delete(out.joints, [10, 11, 12], 0),
                                  np.delete(cap.joints, [10, 11, 12], 0))  # fmt: skip


def test_no_pair_fits_the_joint_is_contradicted_and_kept():
    cap = Capture()
    for f in (20, 21):
        cap.wrong_elbow(f, wrong_views=[1, 2], seen_views=[1, 2])  # both views agree, wrongly
    out = cap.check()
    assert out.contradicted[20:22, ELBOW].all()
    assert not out.contradicted[20:22, WRIST].any()  # seen alike by all five views
    assert not out.resolved.any()
    np.testing.assert_array_equal(out.joints, cap.joints)  # kept for the viewer to show


def test_three_agreeing_views_are_trusted():
    cap = Capture()
    cap.wrong_elbow(25, wrong_views=[1, 2, 3], seen_views=[1, 2, 3])
    out = cap.check()
    assert not out.contradicted.any() and not out.resolved.any()
    # ... unless three views are not enough to be trusted
    out = cap.check(ProportionParams(trusted_views=4))
    assert out.contradicted[25, ELBOW]


def test_disabled_check_changes_nothing_and_short_tracks_have_no_medians():
    cap = Capture()
    cap.wrong_elbow(10, wrong_views=[2, 3], seen_views=[0, 1, 2, 3])
    off = cap.check(ProportionParams(enabled=False))
    assert not off.resolved.any() and not off.contradicted.any()
    short = cap.check(ProportionParams(min_track_frames=F + 1))
    assert np.isnan(short.bone_median).all() and not short.resolved.any()


def test_without_2d_evidence_a_wrong_joint_is_only_flagged():
    cap = Capture()
    cap.wrong_elbow(10, wrong_views=[2, 3], seen_views=[0, 1, 2, 3])
    out = check_proportions(cap.joints, np.zeros(F, int), 1, BONES, None)
    assert out.contradicted[10, ELBOW] and not out.resolved.any()


def test_kalman_skips_contradicted_measurements_and_reports_them():
    truth = np.linspace(0, 290, 30)[:, None, None] * np.ones((1, 1, 3))  # (T, 1, 3) mm
    z = truth.copy()
    z[15] += 400.0  # a wrong joint
    skip = np.zeros((30, 1), bool)
    skip[15] = True
    params = KalmanParams(q=100.0, max_gap=10)
    taken = kalman_filter(z, params)
    skipped = kalman_filter(z, params, skip=skip)
    assert np.abs(taken.forward[15] - truth[15]).max() > 100
    assert np.abs(skipped.forward[15] - truth[15]).max() < 5
    assert skipped.rejected[15, 0] and not taken.rejected[15, 0]
    assert np.linalg.norm(skipped.innovation[15, 0]) > 600  # what it would have been
    with pytest.raises(ValueError, match="skip must be"):
        kalman_filter(z, params, skip=skip[:10])


def test_kalman_takes_a_skipped_measurement_rather_than_drop_the_trajectory():
    z = np.full((20, 1, 3), np.nan)
    z[0:3] = 0.0
    z[14] = 5.0  # after a gap of 10 frames: skipping it would drop the trajectory
    skip = np.zeros((20, 1), bool)
    skip[14] = True
    out = kalman_filter(z, KalmanParams(max_gap=10), skip=skip)
    assert np.isfinite(out.forward[14]).all() and not out.rejected[14, 0]
    # before the gap is that long, the same measurement is skipped
    z2 = z.copy()
    z2[5], z2[14] = 5.0, np.nan
    skip2 = np.zeros((20, 1), bool)
    skip2[5] = True
    out2 = kalman_filter(z2, KalmanParams(max_gap=10), skip=skip2)
    assert out2.rejected[5, 0]


def test_the_run_keeps_flags_in_its_results(tmp_path):
    """A whole run on a scene carries the arrays, and they survive saving."""
    from pipeline.body.model import load_body_model
    from pipeline.data.scene import load_scene
    from pipeline.results.store import load_results, save_results
    from pipeline.run.pipeline import run_pipeline
    from tests.conftest import REPO

    scene = load_scene(REPO / "sample_data" / "shelf_synth_noisy")
    cfg = PipelineConfig(fit_smpl=False)
    res = run_pipeline(scene, cfg, load_body_model(), progress=False)
    assert res.track_resolved.shape == res.track_raw.shape[:3]
    assert res.track_contradicted.shape == res.track_raw.shape[:3]
    save_results(res, tmp_path / "r.npz")
    back = load_results(tmp_path / "r.npz")
    np.testing.assert_array_equal(back.track_resolved, res.track_resolved)
    np.testing.assert_array_equal(back.track_contradicted, res.track_contradicted)
    off = run_pipeline(
        scene, PipelineConfig(fit_smpl=False).with_overrides(["proportions.enabled=false"]),
        load_body_model(), progress=False,
    )  # fmt: skip
    assert not off.track_resolved.any() and not off.track_contradicted.any()
    # the noisy twin has wrong joints of both kinds, and the check lowers the filter's error
    assert res.track_resolved.sum() > 10 and res.track_contradicted.sum() > 10
    from pipeline.evaluation.evaluate import evaluate

    with_check, without = evaluate(scene, res).stages, evaluate(scene, off).stages
    assert with_check["rts"]["mpjpe"] < without["rts"]["mpjpe"] - 0.3
