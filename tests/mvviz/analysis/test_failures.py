"""Failure review: planted failures rank first in their criterion; notes round trip; the
panel jumps to what failed, in-process and in a real browser (headless chromium).

The tiny scene: 2 synthetic people, 20 frames, the 3-camera campus rig, no videos.
"""

from __future__ import annotations

import dataclasses
import json
import time

import numpy as np
import pytest

from mvviz.analysis.failures import (
    CRITERIA,
    MERGE_GAP,
    Failure,
    Note,
    all_failures,
    available_criteria,
    camera_label,
    find_failures,
    kind_counts,
    load_notes,
    new_note,
    notes_path,
    rank,
    save_notes,
    seeing_view,
)
from mvviz.app import ViewerApp
from mvviz.panels.failure_panel import MAX_ENTRIES, make_failure_panel
from mvviz.state import ViewerState
from pipeline.body import pose_limits
from pipeline.body.model import load_body_model
from pipeline.config import PipelineConfig
from pipeline.core.files import SceneFormatError
from pipeline.data.joint_sets import COCO17, SMPL24, mapping_indices
from pipeline.data.scene import load_scene
from pipeline.evaluation import metrics
from pipeline.evaluation.evaluate import evaluate
from pipeline.importers.calibration import read_voxelpose_calibration
from pipeline.run.frames import run_frames, select_2d
from pipeline.run.pipeline import run_pipeline, run_stages
from pipeline.synth.scene_gen import SynthConfig, write_synth_scene
from tests.mvviz.conftest import (
    CAMPUS,
    REPO,
    free_port,
    keep_screenshot,
    open_tab,
    open_viewer,
    settle,
)

NAMES = COCO17.names
DOCS = REPO / "docs" / "screenshots"

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
# the criteria of a scene with ground truth but no stored Shelf / Campus protocol truth
WITHOUT_PROTOCOL = tuple(c for c in CRITERIA if c != "protocol")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """(scene, results): 2 people, 20 frames on the campus rig, no videos."""
    model = load_body_model()
    root = tmp_path_factory.mktemp("failures") / "scene"
    write_synth_scene(
        root,
        read_voxelpose_calibration(CAMPUS),
        model,
        SynthConfig(num_people=2, num_frames=20, seed=3, render_video=False),
        progress=False,
    )
    scene = load_scene(root)
    return scene, run_pipeline(scene, PipelineConfig(), model, progress=False)


def every_finite_edge(scene, res):
    """``res`` with the edges results held before version 6: every pair of detections
    of a frame with a finite affinity (the incompatible ones too)."""
    config = res.config
    frames = run_frames(scene, config, select_2d(scene, config, None), progress=False)
    parts = []
    for fr in frames:
        ia, ib = np.triu_indices(len(fr.rows), 1)
        aff = fr.association.affinity[ia, ib]
        k = np.isfinite(aff)
        dist = fr.association.ray_distance[ia[k], ib[k]]
        parts.append((fr.rows[ia[k]], fr.rows[ib[k]], aff[k], dist))
    a, b, aff, dist = (np.concatenate(x) for x in zip(*parts, strict=True))
    return dataclasses.replace(res, edge_a=a, edge_b=b, edge_affinity=aff, edge_distance=dist)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["tiny", "shelf_synth_noisy"])
def test_the_edges_kept_give_the_failures_every_edge_gives(name, tiny):
    """Results keep a person's own pairs and the compatible ones (affinity > 0): what the
    association criterion reads. With every finite pair it finds the same failures."""
    if name == "tiny":
        scene, res = tiny
    else:
        scene = load_scene(REPO / "sample_data" / name)
        config = PipelineConfig()
        res = run_stages(scene, config, select_2d(scene, config, None), restored=None,
                         progress=False)  # fmt: skip
    full = every_finite_edge(scene, res)
    assert res.edge_a.dtype == np.int32 and res.edge_affinity.dtype == np.float32
    same = (res.det_person[full.edge_a] >= 0) & (
        res.det_person[full.edge_a] == res.det_person[full.edge_b]
    )
    assert len(res.edge_a) == int(((full.edge_affinity > 0) | same).sum())
    assert len(res.edge_a) < len(full.edge_a)
    got = find_failures(scene, res, criterion="association")
    want = find_failures(scene, full, criterion="association")
    close = [f for f in want if f.kind.startswith("close to two")]
    print(f"\n{name}: {len(res.edge_a)} of {len(full.edge_a)} edges kept; "
          f"{len(want)} association failures, {len(close)} close to two")  # fmt: skip
    assert [(f.frame, f.track, f.view, f.kind) for f in got] == [
        (f.frame, f.track, f.view, f.kind) for f in want
    ]
    np.testing.assert_allclose([f.score for f in got], [f.score for f in want], rtol=1e-6)


def person_at(results, frame: int, track: int) -> int:
    q = np.flatnonzero((results.person_frame == frame) & (results.person_track == track))
    assert len(q) == 1
    return int(q[0])


def spans_apart(failures) -> bool:
    """Entries of one problem (kind, track, joint, view) neither overlap nor touch: the
    frames of one problem are one entry."""
    by_key: dict[tuple, list] = {}
    for f in failures:
        joint = None if f.criterion in ("kalman", "mpjpe") else f.joint
        key = (f.kind, f.track, joint, None if f.criterion == "reprojection" else f.view)
        by_key.setdefault(key, []).append((f.first, f.last))
    for spans in by_key.values():
        spans.sort()
        for (_, last), (first, _) in zip(spans, spans[1:], strict=False):
            if first - last <= MERGE_GAP + 1:
                return False
    return True


# --------------------------------------------------------------------------- criteria


def test_every_criterion_ranks_worst_first(tiny):
    scene, res = tiny
    assert available_criteria(scene, res) == WITHOUT_PROTOCOL  # no protocol truth stored
    for c in CRITERIA:
        found = find_failures(scene, res, criterion=c)
        scores = [f.score for f in found]
        assert scores == sorted(scores, reverse=True), c
        assert len(found) <= 50
        assert find_failures(scene, res, criterion=c, top=3) == found[:3]
        for f in found:
            assert f.criterion == c and 0 <= f.first <= f.frame <= f.last < scene.num_frames
            assert 1 <= f.frames <= f.last - f.first + 1
            assert f.track is None or 0 <= f.track < res.num_tracks
            assert f.joint is None or 0 <= f.joint < len(NAMES)
            assert f.view is None or 0 <= f.view < len(scene.rig)
            assert f.text.startswith(f"f {f.first}") and "cam cam" not in f.text
        assert spans_apart(all_failures(scene, res, criterion=c)), c
    with pytest.raises(ValueError, match="unknown failure criterion"):
        find_failures(scene, res, criterion="vibes")


def test_reprojection_spike_ranks_first(tiny):
    scene, res = tiny
    f, k, j, v = 7, 1, NAMES.index("left_wrist"), 2
    q = person_at(res, f, k)
    reproj, used = res.person_reproj.copy(), res.person_used.copy()
    reproj[q, j, v], used[q, j, v] = 99.0, True
    other = person_at(res, 11, 0)  # a bigger error in a view triangulation did not use
    reproj[other, j, 0], used[other, j, 0] = 500.0, False
    planted = dataclasses.replace(res, person_reproj=reproj, person_used=used)
    found = find_failures(scene, planted, criterion="reprojection")
    first = found[0]
    assert (first.frame, first.track, first.joint, first.view) == (f, k, j, v)
    usual = np.nanmedian(np.where(res.person_used, res.person_reproj, np.nan)[:, j, v])
    assert first.value == pytest.approx(99.0)
    assert first.score == pytest.approx(99.0 / max(usual, 1.0), rel=0.01)
    assert first.text.startswith(f"f 7 · track 1 · left_wrist · cam {scene.rig.names[v]} · 99.0 px")
    assert spans_apart(found)
    assert all(x.score < first.score for x in found[1:])
    # scores are relative: every entry is at least twice its joint's usual error there
    assert all(x.score >= 2.0 for x in found)


def test_reprojection_ranks_problems_not_the_outlier_limit(tiny):
    """A camera whose left wrist always reprojects at 18.8-19.9 px (just under the 20 px
    outlier limit) is its usual, not a problem: a 3-frame error of 12x the usual in another
    joint ranks first, merged into one entry with its span."""
    scene, res = tiny
    j_far, j, v = NAMES.index("left_wrist"), NAMES.index("right_knee"), 1
    reproj, used = res.person_reproj.copy(), res.person_used.copy()
    rng = np.random.default_rng(0)
    q_all = np.flatnonzero(np.isfinite(reproj[:, j_far, 0]))
    reproj[q_all, j_far, 0] = rng.uniform(18.8, 19.9, len(q_all))
    usual = np.nanmedian(np.where(used, reproj, np.nan)[:, j, v])
    for f in (4, 5, 6):
        q = person_at(res, f, 0)
        reproj[q, j, v], used[q, j, v] = 12.0 * max(usual, 1.0), True
    planted = dataclasses.replace(res, person_reproj=reproj, person_used=used)
    found = find_failures(scene, planted, criterion="reprojection")
    first = found[0]
    assert (first.first, first.last, first.frames, first.track) == (4, 6, 3, 0)
    assert (first.joint, first.view) == (j, v) and "(3 frames, worst f" in first.text
    assert not [x for x in found if (x.joint, x.view) == (j_far, 0)]
    # one entry per track and joint, whichever camera is worst frame by frame
    assert len({(x.track, x.joint) for x in found}) == len(found)
    assert spans_apart(found)


def test_mahalanobis_spike_ranks_first(tiny):
    scene, res = tiny
    f, k, j = 12, 1, NAMES.index("nose")
    m = res.track_mahalanobis.copy()
    m[k, f, j] = 50.0
    found = find_failures(scene, dataclasses.replace(res, track_mahalanobis=m), criterion="kalman")
    assert (found[0].frame, found[0].track, found[0].joint, found[0].view) == (f, k, j, None)
    assert found[0].score == 50.0 and "Mahalanobis 50.0" in found[0].text
    assert all(x.score > 3.0 for x in found) and spans_apart(found)
    # the threshold is the one asked for
    clean = np.nanmax(res.track_mahalanobis)
    assert find_failures(scene, res, criterion="kalman", mahalanobis_threshold=clean) == []
    updated = int((np.nan_to_num(res.track_mahalanobis).max(-1) > 0).sum())  # not frame 0
    assert updated == 2 * (scene.num_frames - 1)
    # every updated frame of a track is over 0: one entry per track spanning them all
    every = find_failures(scene, res, criterion="kalman", mahalanobis_threshold=0.0)
    assert [(x.first, x.last, x.frames) for x in every] == [(1, 19, 19)] * 2
    assert {x.track for x in every} == {0, 1}


def test_a_joint_off_its_bones_is_listed_with_how_far(tiny):
    """A frame's elbow 200 mm further out than its track's arm: flagged as contradicted it
    ranks first, scored by its bone's deviation over the tolerance; re-solved, the entry
    says how far the other views moved it; results without the check have no entries."""
    scene, res = tiny
    f, k, j = 12, 1, NAMES.index("left_elbow")
    q = int(np.flatnonzero((res.person_track == k) & (res.person_frame == f))[0])
    joints = res.person_joints.copy()
    shoulder = joints[q, NAMES.index("left_shoulder")]
    arm = (joints[q, j] - shoulder) / np.linalg.norm(joints[q, j] - shoulder)
    joints[q, j] = joints[q, j] + 200.0 * arm  # the frame's triangulation was off
    flags = np.zeros(res.track_raw.shape[:3], bool)
    flags[k, f, j] = True
    none = np.zeros_like(flags)
    flagged = dataclasses.replace(
        res, person_joints=joints, track_contradicted=flags, track_resolved=none
    )
    found = find_failures(scene, flagged, criterion="proportions")
    assert len(found) == 1
    e = found[0]
    assert (e.frame, e.track, e.joint, e.kind) == (f, k, j, "contradicted")
    raw = res.track_raw[k]  # the elbow's two bones against their medians over the track
    others = [NAMES.index("left_shoulder"), NAMES.index("left_wrist")]
    expected = max(
        abs(
            np.linalg.norm(joints[q, j] - joints[q, o])
            / np.nanmedian(np.linalg.norm(raw[:, j] - raw[:, o], axis=-1))
            - 1
        )
        for o in others
    )
    assert e.value == pytest.approx(expected, rel=0.05)
    assert e.score == pytest.approx(e.value / res.config.proportions.tolerance)
    moved = dataclasses.replace(flagged, track_contradicted=none, track_resolved=flags)
    (r,) = find_failures(scene, moved, criterion="proportions")
    assert r.kind == "re-solved" and "moved 200 mm" in r.text
    assert (
        find_failures(
            scene,
            dataclasses.replace(res, track_contradicted=none, track_resolved=none),
            criterion="proportions",
        )
        == []
    )
    old = dataclasses.replace(res, track_contradicted=None, track_resolved=None)
    assert "proportions" not in available_criteria(scene, old)


def test_frames_where_the_prior_backed_off_are_listed(tiny):
    """Where the correction kept step I's pose the two fits' poses are equal, and the
    failure review lists those person-frames under the SMPL criterion."""
    scene, res = tiny
    fit = res.smpl_vae
    assert fit.prior_reverted is not None and fit.prior_reverted.shape == fit.present.shape
    k, f = np.nonzero(fit.prior_reverted)
    np.testing.assert_array_equal(fit.pose_rotvecs[k, f], res.smpl.pose_rotvecs[k, f])
    flags = np.zeros_like(fit.prior_reverted)
    flags[1, 7:9] = True
    moved = dataclasses.replace(res, smpl_vae=dataclasses.replace(fit, prior_reverted=flags))
    backed = [
        x for x in all_failures(scene, moved, criterion="smpl") if x.kind == "prior backed off"
    ]
    assert [(x.track, x.first, x.last) for x in backed] == [(1, 7, 8)]
    assert "step I's pose kept" in backed[0].text


def test_ground_truth_offset_ranks_first_in_mpjpe(tiny):
    scene, res = tiny
    gt = scene.gt
    f, pid, j = 9, int(np.unique(gt.person_id)[0]), NAMES.index("left_wrist")
    row = int(np.flatnonzero((gt.frame == f) & (gt.person_id == pid))[0])
    kp = gt.keypoints3d.copy()
    kp[row, j] += (1000.0, 0.0, 0.0)
    moved = dataclasses.replace(scene, gt=dataclasses.replace(gt, keypoints3d=kp))
    # the track following that person: nearest to its truth in that frame
    err = np.nanmean(np.linalg.norm(res.track_filtered[:, f] - gt.keypoints3d[row], axis=-1), 1)
    k = int(np.argmin(err))
    src = mapping_indices(COCO17, SMPL24)[0]
    clean = metrics.mpjpe(res.track_filtered[k, f, src], gt.keypoints3d[row, src])
    found = find_failures(moved, res, criterion="mpjpe")
    first = found[0]
    assert (first.frame, first.track, first.joint) == (f, k, j)
    assert "left_wrist" in first.text and f"GT {pid}" in first.text
    # 1000 mm on one of the n joints both sets share raises MPJPE by about 1000 / n mm
    n = len(src)
    delta = first.value - clean
    assert 1000 / n - 5 < delta <= 1000 / n + 1e-6
    assert first.score >= 2.0 and spans_apart(found)
    # no ground truth: nothing to rank, and the panel does not offer it
    no_gt = dataclasses.replace(scene, gt=None)
    assert find_failures(no_gt, res, criterion="mpjpe") == []
    assert "mpjpe" not in available_criteria(no_gt, res)


def test_association_conflict_and_gap_rank_first(tiny):
    scene, res = tiny
    f = 5
    qa, qb = person_at(res, f, 0), person_at(res, f, 1)
    # planted edges: detection a of person qa as close to every detection of person qb in
    # the other views as can be (the results keep no edge between two people that are
    # apart: affinity <= 0), and only loosely with its own person's (0.6): a doubt
    view = scene.detections.view
    a = int(np.flatnonzero(res.det_person == qa)[0])
    bs = np.flatnonzero((res.det_person == qb) & (view != view[a]))
    assert len(bs) >= 2
    own = ((res.edge_a == a) | (res.edge_b == a)) & (
        res.det_person[res.edge_a] == res.det_person[res.edge_b]
    )
    assert own.sum() >= 1

    def plant(rows):
        loose = np.where(own, np.float32(0.6), res.edge_affinity)
        ends = ((res.edge_a == a) & np.isin(res.edge_b, bs)) | (
            (res.edge_b == a) & np.isin(res.edge_a, bs)
        )
        loose[ends] = 0.0  # the pairs' own edges, if any, are replaced by the planted ones
        return dataclasses.replace(
            res,
            edge_a=np.append(res.edge_a, np.full(len(rows), a, np.int32)),
            edge_b=np.append(res.edge_b, rows.astype(np.int32)),
            edge_affinity=np.append(loose, np.full(len(rows), 0.99, np.float32)),
            edge_distance=np.append(res.edge_distance, np.ones(len(rows), np.float32)),
        )  # fmt: skip

    found = find_failures(scene, plant(bs), criterion="association")
    first = found[0]
    agreement = 0.99 * len(bs) / int((res.det_person == qb).sum())
    assert first.frame == f and first.score == pytest.approx(agreement, rel=1e-6)
    assert (first.track, first.view) == (0, int(view[a]))
    assert "close to track 1" in first.text
    # one pair of rays passing near each other is not a doubt: one planted edge alone
    one = find_failures(scene, plant(bs[:1]), criterion="association")
    assert not [x for x in one if x.kind.startswith("close to two") and x.frame == f]
    # a gap in track 0's raw triangulation (present before and after) ranks first
    raw = res.track_raw.copy()
    raw[0, 8:10] = np.nan
    gap = find_failures(scene, dataclasses.replace(res, track_raw=raw), criterion="association")
    assert (gap[0].first, gap[0].last, gap[0].track, gap[0].kind) == (8, 9, 0, "missing in raw")
    assert gap[0].score == pytest.approx(1.0 + 2 / 20)
    assert gap[0].text == "f 8–9 · track 0 · missing in raw (2 frames, worst f 8)"
    # confident unassigned detections are listed with their view, frames merged
    conf = np.nanmean(res.det_joints2d[..., 2], 1)
    rows = np.flatnonzero((res.det_person < 0) & (conf >= 0.3))
    listed = [x for x in all_failures(scene, res, criterion="association") if x.track is None]
    for d in rows:
        fd, vd = int(scene.detections.frame[d]), int(view[d])
        assert any(x.view == vd and x.first <= fd <= x.last for x in listed)


def test_births_deaths_and_id_switches(tiny):
    scene, res = tiny
    assert find_failures(scene, res, criterion="id") == []  # both tracks span the clip
    raw = res.track_raw.copy()
    raw[1, :5] = np.nan  # track 1 is born at frame 5
    raw[0, 15:] = np.nan  # track 0 dies after frame 14
    found = find_failures(scene, dataclasses.replace(res, track_raw=raw), criterion="id")
    assert [(x.frame, x.track, x.score) for x in found] == [(5, 1, 1.25), (14, 0, 1.25)]
    assert "born" in found[0].text and "last seen" in found[1].text
    # tracks swap identities from frame 10: switches rank above births and deaths
    swapped = res.track_raw.copy()
    swapped[:, 10:] = swapped[::-1, 10:]
    switched = dataclasses.replace(res, track_raw=swapped)
    events = evaluate(scene, switched).id_switch_events
    assert len(events) == 2 and {e[0] for e in events} == {10}
    found = find_failures(scene, switched, criterion="id")
    assert [(x.frame, x.score) for x in found] == [(10, 3.0), (10, 3.0)]
    assert {x.track for x in found} == {0, 1} and all("ID switch" in x.text for x in found)


def limits(found):
    """The joint-limit entries of an SMPL list (their own order; residuals rank apart)."""
    return [x for x in found if x.kind == "joint limit"]


def with_filtered(res, filt):
    return dataclasses.replace(res, track_forward=filt, track_smoothed=filt)


def test_smpl_residual_and_joint_limit_rank_first(tiny):
    scene, res = tiny
    fit = res.smpl_vae
    assert fit is not None
    residual = fit.residual.copy()
    residual[0, 6, NAMES.index("left_knee")] = 2000.0
    planted = dataclasses.replace(res, smpl_vae=dataclasses.replace(fit, residual=residual))
    first = find_failures(scene, planted, criterion="smpl")[0]
    assert (first.frame, first.track, first.joint) == (6, 0, NAMES.index("left_knee"))
    assert first.value == pytest.approx(2000) and "residual 2000 mm" in first.text
    assert first.kind == "residual" and first.score > 10
    # an elbow bent backwards by 143 degrees (flexion limits 0..150)
    pose = fit.pose_rotvecs.copy()
    pose[1, 3, SMPL24.index["left_elbow"]] = (0.0, 2.5, 0.0)
    bent = dataclasses.replace(res, smpl_vae=dataclasses.replace(fit, pose_rotvecs=pose))
    first = limits(find_failures(scene, bent, criterion="smpl"))[0]
    excess = pose_limits.limit_excess(pose[1, 3])[SMPL24.index["left_elbow"]]
    assert excess == pytest.approx(np.rad2deg(2.5), abs=0.5)
    assert (first.frame, first.track, first.joint) == (3, 1, NAMES.index("left_elbow"))
    assert first.score == pytest.approx(excess / 10)
    assert "left_elbow · flexion -143° outside [0°, 150°]" in first.text
    # a joint COCO-17 lacks is still named, with no joint index
    pose = fit.pose_rotvecs.copy()
    pose[0, 2, SMPL24.index["spine2"]] = (0.0, 0.0, 2.8)  # side bend 160 deg
    spine = limits(
        find_failures(
            scene,
            dataclasses.replace(res, smpl_vae=dataclasses.replace(fit, pose_rotvecs=pose)),
            criterion="smpl",
        )
    )[0]
    assert (spine.frame, spine.track, spine.joint) == (2, 0, None) and "spine2" in spine.text


def test_mpjpe_entries_agree_with_metrics(tiny):
    """Each listed MPJPE is the mean joint error of the pair metrics.match_people made."""
    scene, res = tiny
    kp = scene.gt.keypoints3d
    src, dst = mapping_indices(COCO17, SMPL24)
    filt = res.track_filtered.copy()
    filt[1, 3:6] += 200.0  # 346 mm off on every joint for 3 frames
    found = find_failures(scene, with_filtered(res, filt), criterion="mpjpe")
    assert found and found[0].kind == "MPJPE" and found[0].track == 1
    assert (found[0].first, found[0].last) == (3, 5)
    for x in found:
        rows = np.flatnonzero(scene.gt.frame == x.frame)
        errs = [metrics.mpjpe(filt[x.track, x.frame, src], kp[r, src]) for r in rows]
        assert min(errs) == pytest.approx(x.value)
    assert len(dst) == 12


def test_label_check_names_the_mirrored_track_and_camera(tiny):
    """A track with left/right swapped and a camera whose 2D is mirrored are listed with
    the track / camera and a frame to jump to; the clean run lists nothing."""
    scene, res = tiny
    assert find_failures(scene, res, criterion="labels") == []
    raw = res.track_raw.copy()
    raw[1] = raw[1][:, COCO17.flip_index]
    kp = res.det_joints2d.copy()
    v = 2
    rows = scene.detections.view == v
    kp[rows] = kp[rows][:, COCO17.flip_index]
    planted = dataclasses.replace(res, track_raw=raw, det_joints2d=kp)
    found = find_failures(scene, planted, criterion="labels")
    facing = [x for x in found if "face the other way" in x.text]
    assert [(x.track, x.view, x.frame) for x in facing] == [(1, None, 0)]
    assert facing[0].score == pytest.approx(1.0 / 0.3)  # every frame, threshold 30 %
    assert facing[0].text.startswith("f 0 · track 1 · head/feet face the other way")
    cam = [x for x in found if x.view is not None]
    assert len(cam) == 1 and cam[0].track is None and cam[0].view == v
    assert cam[0].text.startswith(f"f {cam[0].frame} · cam {scene.rig.names[v]} · 2D fits")
    assert camera_label("cam03") == "cam03" and camera_label("3") == "cam 3"
    assert cam[0].score == pytest.approx(2.0)  # all its people mirrored, threshold 50 %
    assert {x.track for x in found} <= {1, None}


def test_disabled_cameras_are_left_out(tiny):
    """A camera switched off in the Pipeline panel (config.disabled_views) names no entry
    (its detections are all unassigned then, which is not a problem) and is never the
    camera a jump shows."""
    scene, res = tiny
    name = scene.rig.names[2]
    off = dataclasses.replace(res, config=dataclasses.replace(res.config, disabled_views=(name,)))
    for c in CRITERIA:
        assert all(x.view != 2 for x in all_failures(scene, off, criterion=c)), c
    gap = Failure("association", 1.0, 8, 0, None, None, "track 0", "missing in raw")
    assert seeing_view(scene, off, gap) in (0, 1)


def test_jump_picks_a_camera_that_sees_the_person(tiny):
    """An entry naming no camera shows the one whose detection of the person is most
    confident; where the track is missing, the camera its nearest pose projects into."""
    scene, res = tiny
    f, k = 8, 0
    q = person_at(res, f, k)
    members = res.person_members[q]
    conf = [
        np.nanmean(res.det_joints2d[members[v], :, 2]) if members[v] >= 0 else -1
        for v in range(len(scene.rig))
    ]
    gap = Failure("association", 1.0, f, k, None, None, "track 0", "missing in raw")
    assert seeing_view(scene, res, gap) == int(np.argmax(conf))
    # the track is missing in frames 7-9: no person of it there at all
    ptrack = res.person_track.copy()
    ptrack[(res.person_frame >= 7) & (res.person_frame <= 9) & (ptrack == k)] = -1
    raw, filt = res.track_raw.copy(), res.track_filtered.copy()
    raw[k, 7:10] = np.nan
    filt[k, 7:10] = np.nan
    missing = dataclasses.replace(with_filtered(res, filt), person_track=ptrack, track_raw=raw)
    v = seeing_view(scene, missing, gap)
    assert v is not None
    cam = scene.rig[v]
    uv = cam.project(res.track_filtered[k, 6])  # the pose just before the gap
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    assert inside.mean() > 0.9
    # an entry naming a camera keeps it
    named = dataclasses.replace(gap, view=2)
    assert seeing_view(scene, res, named) == 2
    assert seeing_view(scene, res, dataclasses.replace(gap, track=None)) is None


def test_kind_counts_rank_the_kinds(tiny):
    scene, res = tiny
    raw = res.track_raw.copy()
    raw[0, 8:10] = np.nan
    raw[1, 3:4] = np.nan
    found = all_failures(scene, dataclasses.replace(res, track_raw=raw), criterion="association")
    counts = kind_counts(found)
    assert counts["missing in raw"] == 2
    assert list(counts.values()) == sorted(counts.values(), reverse=True)
    assert rank(found, 3) == find_failures(
        scene, dataclasses.replace(res, track_raw=raw), criterion="association", top=3
    )


# --------------------------------------------------------------------------- notes


def test_notes_round_trip(tmp_path):
    path = notes_path(tmp_path)
    assert path == tmp_path / ".mvviz" / "notes.json"
    assert load_notes(path) == []
    notes = [
        new_note(3, "left wrist flips"),
        Note(7, "ünïcode ✓ two\nlines", "2024-05-01T10:00:00+02:00"),
    ]
    save_notes(path, notes)
    assert load_notes(path) == notes
    assert json.loads(path.read_text())["version"] == 1
    assert not list(path.parent.glob(".notes.json.*"))  # no temporary file left behind


def test_corrupt_notes_raise_a_clear_error(tmp_path):
    path = notes_path(tmp_path)
    path.parent.mkdir(parents=True)
    path.write_text('{"version": 1, "notes": [')
    with pytest.raises(SceneFormatError, match=str(path)) as info:
        load_notes(path)
    assert "not a readable notes file" in str(info.value)
    path.write_text(json.dumps({"version": 1, "notes": [{"frame": -2, "text": "", "created": ""}]}))
    with pytest.raises(SceneFormatError, match=r"notes\[0\]\.frame"):
        load_notes(path)
    path.write_text(
        json.dumps({"version": 1, "notes": [{"frame": 2, "text": "x", "created": "x"}]})
    )
    with pytest.raises(SceneFormatError, match=r"notes\[0\]\.created.*not an ISO time"):
        load_notes(path)


# --------------------------------------------------------------------------- panel


@pytest.fixture(scope="module")
def app(tiny):
    scene, res = tiny
    a = ViewerApp(ViewerState.create(scene, res), host="127.0.0.1", port=free_port())
    assert a.wait_idle(30) and a.failure_panel.wait_idle(30)
    yield a
    a.stop()


@pytest.fixture
def no_notes(tiny):
    path = notes_path(tiny[0].root)
    path.unlink(missing_ok=True)
    yield path
    path.unlink(missing_ok=True)


def test_panel_lists_and_jumps(app, tiny):
    scene, res = tiny
    panel = app.failure_panel
    assert panel.criteria == WITHOUT_PROTOCOL
    for c in ("kalman", "reprojection"):
        panel.set_criterion(c)
        assert panel.wait_idle()
        every = all_failures(scene, res, criterion=c)
        want = rank(every, MAX_ENTRIES)
        assert panel.failures == want and panel.found == len(every)
        shown = [b for b in panel.gui.entries if b.visible]
        assert len(shown) == len(want)
        # the button: span and track; the line below it: the whole text, wrapping
        assert shown[0].label == f"1. {want[0].head}"
        details = panel.gui.details[0].content.replace("\\_", "_")
        assert want[0].text[len(want[0].span) :].lstrip(" ·") in details
        assert all(
            f"{k} **{n}**" in panel.gui.summary.content for k, n in kind_counts(every).items()
        )
    deadline = time.monotonic() + 10
    while set(panel.counts) != set(WITHOUT_PROTOCOL) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert panel.counts == {c: len(all_failures(scene, res, criterion=c)) for c in WITHOUT_PROTOCOL}
    assert "MPJPE" in panel.gui.overview.content and "Kalman" in panel.gui.overview.content
    app.set_frame(0)
    first = panel.click(0)  # reprojection: names a view
    assert app.wait_idle()
    assert int(app.timeline.gui.slider.value) == first.frame == app.state.frame
    assert app.state.selection.track == first.track
    assert app.state.selection.joint == first.joint
    assert app.camera_panel.gui.camera.value == scene.rig.names[first.view]
    assert panel.gui.entries[0].color == "orange"
    # an entry naming no camera: the camera panel shows one that sees the person
    panel.set_criterion("kalman")
    assert panel.wait_idle()
    k_entry = panel.click(0)
    assert app.wait_idle() and k_entry.view is None
    v = seeing_view(scene, res, k_entry)
    assert app.camera_panel.gui.camera.value == scene.rig.names[v]
    q = person_at(res, k_entry.frame, k_entry.track)
    assert res.person_members[q, v] >= 0


def test_panel_follows_new_results(app, tiny):
    scene, res = tiny
    panel = app.failure_panel
    panel.set_criterion("kalman")
    m = res.track_mahalanobis.copy()
    m[0, 4, NAMES.index("right_ankle")] = 77.0
    app.set_results(dataclasses.replace(res, track_mahalanobis=m))
    try:
        assert app.wait_idle() and panel.wait_idle()
        deadline = time.monotonic() + 10
        while panel.failures[0].score != 77.0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert (panel.failures[0].frame, panel.failures[0].track) == (4, 0)
        assert panel.gui.entries[0].label == f"1. {panel.failures[0].span} · track 0"
        assert "right\\_ankle · Mahalanobis 77.0" in panel.gui.details[0].content
    finally:
        app.set_results(res)
        assert app.wait_idle()
        time.sleep(0.2)
        assert panel.wait_idle()


def test_panel_notes_flag_reload_delete(app, no_notes):
    panel = app.failure_panel
    app.set_frame(6)
    assert app.wait_idle()
    panel.gui.note_text.value = "left wrist flips"
    note = panel.flag()
    assert note.frame == 6 and note.text == "left wrist flips"
    assert load_notes(no_notes) == [note]  # saved at once
    assert panel.gui.note_text.value == ""
    other_viewer = Note(2, "late start", "2024-05-01T10:00:00+02:00")
    save_notes(no_notes, [other_viewer, note])  # another viewer saved one meanwhile
    panel.flag("elbow", frame=9)
    assert [n.frame for n in load_notes(no_notes)] == [2, 6, 9]
    # a fresh panel (a viewer restart) reads them back
    again = make_failure_panel(app)
    try:
        assert [n.text for n in again.notes] == ["late start", "left wrist flips", "elbow"]
        assert [b.label for b in again.gui.note_buttons if b.visible] == [
            "f 2 · late start",
            "f 6 · left wrist flips",
            "f 9 · elbow",
        ]
        again.select_note(1)
        assert app.wait_idle() and app.state.frame == 6
        assert again.gui.note_buttons[1].color == "orange"
        assert again.delete_selected() == note
        assert load_notes(no_notes) == again.notes and len(again.notes) == 2
        assert again.gui.delete.disabled and again.delete_selected() is None
    finally:
        again.remove()


def test_panel_leaves_a_corrupt_notes_file_alone(app, no_notes):
    no_notes.parent.mkdir(parents=True, exist_ok=True)
    no_notes.write_text("{ half a file")
    panel = make_failure_panel(app)
    try:
        assert panel.notes_error is not None and str(no_notes) in panel.notes_error
        assert "Notes file unreadable" in panel.gui.notes_info.content
        with pytest.raises(SceneFormatError, match=str(no_notes)):
            panel.flag("anything")
        assert no_notes.read_text() == "{ half a file"
        # fixed by hand: flagging works again
        save_notes(no_notes, [])
        assert panel.flag("now it saves", frame=3).frame == 3
        assert [n.text for n in load_notes(no_notes)] == ["now it saves"]
        assert panel.notes_error is None
    finally:
        panel.remove()


# --------------------------------------------------------------------------- browser


@pytest.mark.slow
def test_clicking_a_failure_in_the_page_moves_the_timeline(browser, app, tiny, no_notes, tmp_path):
    scene, res = tiny
    panel = app.failure_panel
    panel.set_criterion("reprojection")
    assert panel.wait_idle()
    app.set_frame(0)
    assert app.wait_idle()
    page = open_viewer(browser, app.url)
    try:
        first = panel.failures[0]
        assert first.frame != 0
        open_tab(page, "Failures")
        button = page.get_by_role("button", name=f"1. {first.head}", exact=True)
        button.scroll_into_view_if_needed()
        button.click()
        deadline = time.monotonic() + 10
        while int(app.timeline.gui.slider.value) != first.frame and time.monotonic() < deadline:
            time.sleep(0.05)
        assert int(app.timeline.gui.slider.value) == first.frame
        assert app.wait_idle() and app.state.frame == first.frame
        assert app.camera_panel.gui.camera.value == scene.rig.names[first.view]
        # "Look at it": the page's 3D camera turned to the failing joint (metres)
        target = app.state.data.filtered[first.track, first.frame, first.joint] / 1000
        client = next(iter(app.server.get_clients().values()))
        deadline = time.monotonic() + 5
        while not np.allclose(client.camera.look_at, target, atol=0.05):
            assert time.monotonic() < deadline, f"look_at {client.camera.look_at} != {target}"
            time.sleep(0.05)
        # flag the frame from the page: typed text, button, saved file
        # viser draws a text input's label beside it, not as its <label>
        box = page.locator(
            "xpath=//*[normalize-space(text())='Note']"
            "/following::input[contains(@class, 'mantine-TextInput-input')][1]"
        )
        box.fill("elbow reprojects badly")
        box.press("Enter")
        deadline = time.monotonic() + 5
        while panel.gui.note_text.value != "elbow reprojects badly" and time.monotonic() < deadline:
            time.sleep(0.05)
        page.get_by_role("button", name="Flag this frame").click()
        deadline = time.monotonic() + 10
        while not no_notes.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        notes = load_notes(no_notes)
        assert [(n.frame, n.text) for n in notes] == [(first.frame, "elbow reprojects badly")]
        page.set_viewport_size({"width": 1400, "height": 1000})
        title = page.get_by_text("Failures", exact=True).last  # the folder, not the tab
        title.evaluate("e => e.scrollIntoView({block: 'start'})")
        settle(page, 2.0)
        shot = tmp_path / "failures.png"
        page.screenshot(path=str(shot))
        keep_screenshot(shot, "failures.png")
    finally:
        page.close()


def test_merge_spans_joins_entries_near_any_earlier_entry_of_the_run() -> None:
    """A long entry (f 0-100) keeps its run open past shorter ones inside it: f 103 is
    within MERGE_GAP + 1 of f 100, though not of f 51, the entry just before it."""
    from mvviz.analysis.failures.review import merge_spans

    def entry(first: int, last: int, score: float) -> Failure:
        return Failure("kalman", score, first, 1, 2, None, kind="gap", first=first, last=last)

    merged = merge_spans([entry(50, 51, 3.0), entry(0, 100, 1.0), entry(103, 103, 2.0),
                          entry(107, 108, 5.0), entry(200, 200, 4.0)])  # fmt: skip
    spans = sorted((f.first, f.last, f.frames, f.score) for f in merged)
    assert spans == [(0, 103, 102, 3.0), (107, 108, 1, 5.0), (200, 200, 1, 4.0)]


@pytest.mark.slow
def test_association_failures_read_the_edges_in_blocks(monkeypatch, tmp_path):
    """The association criterion reads the edges block by block (a 10,000-frame run has
    ~200 M): blocks of 997 edges and the whole in one block find the same failures, with
    the same own-affinity figures, also on a results directory (memory-mapped)."""
    import mvviz.analysis.failures.criteria as criteria
    from pipeline.results.store import load_results, save_results

    scene = load_scene(REPO / "sample_data" / "shelf_synth_noisy")
    config = PipelineConfig()
    res = run_stages(scene, config, select_2d(scene, config, None), restored=None,
                     progress=False)  # fmt: skip
    save_results(res, tmp_path / "results")
    mapped = load_results(tmp_path / "results")
    want = find_failures(scene, res, criterion="association")
    assert len(res.edge_a) > 10_000 and any(f.kind.startswith("close to two") for f in want)
    monkeypatch.setattr(criteria, "EDGE_BLOCK", 997)
    for r in (res, mapped):
        got = find_failures(scene, r, criterion="association")
        assert [(f.frame, f.track, f.view, f.kind, f.detail) for f in got] == [
            (f.frame, f.track, f.view, f.kind, f.detail) for f in want
        ]
        np.testing.assert_allclose([f.score for f in got], [f.score for f in want], rtol=1e-12)
    # each detection's agreement with its own person, as the plain definition gives it
    own, _ = criteria._edge_summary(res, criteria.AFFINITY_THRESHOLD)
    size = np.bincount(res.det_person[res.det_person >= 0])
    for d in np.flatnonzero(res.det_person >= 0)[:200]:
        mine = (res.edge_a == d) | (res.edge_b == d)
        other = np.where(res.edge_a[mine] == d, res.edge_b[mine], res.edge_a[mine])
        same = res.det_person[other] == res.det_person[d]
        n_other = size[res.det_person[d]] - 1
        if n_other:
            agree = np.maximum(res.edge_affinity[mine][same].astype(float), 0).sum() / n_other
            assert own[d] == pytest.approx(agree, rel=1e-9, abs=1e-12)
        else:
            assert np.isnan(own[d])


@pytest.mark.slow
def test_reprojection_failures_read_the_errors_in_blocks(monkeypatch, tmp_path):
    """The usual error per joint and camera and the hits over it, a few cameras / rows at
    a time (a 10,000-frame run's errors are 850 MB): the failures of one block."""
    import mvviz.analysis.failures.criteria as criteria
    from pipeline.results.store import load_results, save_results

    scene = load_scene(REPO / "sample_data" / "shelf_synth_noisy")
    config = PipelineConfig()
    res = run_stages(scene, config, select_2d(scene, config, None), restored=None,
                     progress=False)  # fmt: skip
    save_results(res, tmp_path / "results")
    want = find_failures(scene, res, criterion="reprojection", top=10_000)
    assert len(want) > 20
    monkeypatch.setattr(criteria, "REPROJ_BLOCK_VALUES", 500)  # 5 rows, or 1 camera, a block
    for r in (res, load_results(tmp_path / "results")):
        got = find_failures(scene, r, criterion="reprojection", top=10_000)
        assert [(f.frame, f.track, f.joint, f.view, f.detail) for f in got] == [
            (f.frame, f.track, f.joint, f.view, f.detail) for f in want
        ]
        np.testing.assert_array_equal([f.score for f in got], [f.score for f in want])


@pytest.mark.slow
@pytest.mark.parametrize("level", [1.3, 2.0])
def test_reprojection_runs_merged_in_arrays_are_what_merge_spans_makes(level):
    """The reprojection criterion merges its hits into runs in arrays (millions of hits
    on a long run): the entries are those of one entry per hit merged by merge_spans."""
    import mvviz.analysis.failures.criteria as criteria
    from mvviz.analysis.failures.review import merge_spans

    scene = load_scene(REPO / "sample_data" / "shelf_synth_noisy")
    config = PipelineConfig()
    res = run_stages(scene, config, select_2d(scene, config, None), restored=None,
                     progress=False)  # fmt: skip
    usual = criteria._usual_reprojection(res)
    q, j, v, e = criteria._reprojection_hits(res, usual, level)
    names, cams = criteria.joint_names(res), scene.rig.names
    singles = []
    for qi, ji, vi, ei in zip(q.tolist(), j.tolist(), v.tolist(), e.tolist(), strict=True):
        k = criteria.track_or_none(res.person_track[qi])
        r = ei / usual[ji, vi]
        detail = f"{ei:.1f} px, {r:.1f}× its usual {usual[ji, vi]:.1f} px"
        detail += " (untracked person)" if k is None else ""
        singles.append(Failure(
            "reprojection", r, int(res.person_frame[qi]), k, ji, vi,
            criteria.where_label(k, names[ji], cams[vi]), detail, kind="reprojection", value=ei,
        ))  # fmt: skip
    want = merge_spans(singles)
    got = criteria.reprojection_failures(scene, res, level=level)
    assert len(singles) > 2 * len(want) > 20  # runs of several hits were merged
    key = lambda f: (f.track if f.track is not None else -1, f.joint, f.first)  # noqa: E731
    assert sorted(got, key=key) == sorted(want, key=key)


def _close_to_two_plain(scene, res, threshold: float, margin: float) -> list:
    """The "close to two" entries by their plain definition, a loop over the edges: each
    detection's agreement with every other person of its frame (mean of max(affinity, 0)
    over that person's detections) and with its own; per pair of people of a frame the
    detection of highest agreement among those within ``margin`` of their own (lowest
    row of ties), in frame order; then merge_spans."""
    import collections

    import mvviz.analysis.failures.criteria as criteria
    from mvviz.analysis.failures.review import merge_spans

    dp = res.det_person
    size = collections.Counter(int(x) for x in dp if x >= 0)
    sums = collections.defaultdict(float)  # (detection, person) -> sum of max(aff, 0)
    for a, b, aff in zip(res.edge_a.tolist(), res.edge_b.tolist(),
                         res.edge_affinity.tolist(), strict=True):  # fmt: skip
        if dp[a] >= 0 and dp[b] >= 0:
            sums[a, int(dp[b])] += max(aff, 0.0)
            sums[b, int(dp[a])] += max(aff, 0.0)
    best: dict = {}
    for (d, q2), total in sorted(sums.items()):
        q = int(dp[d])
        if q2 == q:
            continue
        agree = total / size[q2]
        own = sums.get((d, q), 0.0) / (size[q] - 1) if size[q] > 1 else None
        if agree < threshold or agree < (own or 0.0) - margin:
            continue
        pair = (min(q, q2), max(q, q2))
        if pair not in best or agree > best[pair][0]:
            best[pair] = (agree, d, q2, own)

    def who(q):
        k = int(res.person_track[q])
        return f"track {k}" if k >= 0 else "an untracked person"

    singles = []
    in_order = sorted(best.values(), key=lambda x: (res.person_frame[dp[x[1]]], x[1]))
    for agree, d, q2, own in in_order:
        q = int(dp[d])
        k = criteria.track_or_none(res.person_track[q])
        v = int(scene.detections.view[d])
        own_txt = f", own {own:.2f}" if own is not None else ", alone in its person"
        singles.append(Failure(
            "association", agree, int(res.person_frame[q]), k, None, v,
            criteria.where_label(k, None, scene.rig.names[v]),
            f"close to {who(q2)} too (mean affinity {agree:.2f} to its {size[q2]} "
            f"detections{own_txt})",
            kind=f"close to two|{who(q2)}", value=agree,
        ))  # fmt: skip
    return singles, merge_spans(singles)


@pytest.mark.slow
@pytest.mark.parametrize("margin", [0.2, 0.6])
def test_close_to_two_is_its_plain_definition(margin):
    """The "close to two" entries, found and merged in arrays, are those of the plain loop
    merged by merge_spans (see _close_to_two_plain); with a wide margin (0.6: most
    agreements above the threshold) consecutive frames of one problem merge."""
    import mvviz.analysis.failures.criteria as criteria
    from mvviz.analysis.failures.review import merge_spans

    scene = load_scene(REPO / "sample_data" / "shelf_synth_noisy")
    config = PipelineConfig()
    res = run_stages(scene, config, select_2d(scene, config, None), restored=None,
                     progress=False)  # fmt: skip
    singles, want = _close_to_two_plain(scene, res, criteria.AFFINITY_THRESHOLD, margin)
    got = criteria._close_to_two(scene, res, criteria.AFFINITY_THRESHOLD, margin)
    assert [(f.frame, f.where, f.detail, f.first, f.last, f.frames) for f in got] == [
        (f.frame, f.where, f.detail, f.first, f.last, f.frames) for f in want
    ]
    np.testing.assert_allclose([f.score for f in got], [f.score for f in want], rtol=1e-9)
    assert merge_spans(got) == got  # all_failures merges again: nothing changes
    if margin > 0.5:
        assert len(singles) > len(want) > 10  # consecutive frames were merged
    else:
        assert 1 <= len(want) <= 10


@pytest.mark.slow
def test_close_to_two_does_not_flag_people_a_pair_of_rays_links():
    """On the clean sample (no association error; people >= ~0.9 m apart) one pair of
    rays from two cameras passes near another person's in ~3 pairs of people a frame
    (the rule before: 759 entries' frames); agreement over the other person's views and
    the margin to its own leave none. The noisy twin: a few, between people whose
    triangulated centres are near."""
    import mvviz.analysis.failures.criteria as criteria

    for name, most in (("shelf_synth", 0), ("shelf_synth_noisy", 5)):
        scene = load_scene(REPO / "sample_data" / name)
        config = PipelineConfig()
        res = run_stages(scene, config, select_2d(scene, config, None), restored=None,
                         progress=False)  # fmt: skip
        pa, pb = res.det_person[res.edge_a], res.det_person[res.edge_b]
        one_pair = (pa >= 0) & (pb >= 0) & (pa != pb) & (res.edge_affinity >= 0.5)
        assert one_pair.sum() > 500  # what a pairwise rule would have listed
        got = criteria._close_to_two(scene, res, criteria.AFFINITY_THRESHOLD,
                                     criteria.CLOSE_MARGIN)  # fmt: skip
        assert len(got) <= most, name


@pytest.mark.slow
def test_agreements_by_place_equal_the_sorted_keys():
    """_agreements sums (detection, other person) by the other's place among its frame's
    people (one bincount); people out of frame order take np.unique's sorted keys: the
    two give the same rows and numbers on the noisy twin's every cross edge."""
    import mvviz.analysis.failures.criteria as criteria

    scene = load_scene(REPO / "sample_data" / "shelf_synth_noisy")
    config = PipelineConfig()
    res = run_stages(scene, config, select_2d(scene, config, None), restored=None,
                     progress=False)  # fmt: skip
    dp = res.det_person
    pa, pb = dp[res.edge_a], dp[res.edge_b]
    c = np.flatnonzero((pa >= 0) & (pb >= 0) & (pa != pb) & (res.edge_affinity > 0))
    rows = (np.r_[res.edge_a[c], res.edge_b[c]].astype(np.int64),
            np.r_[pb[c], pa[c]].astype(np.int64),
            np.tile(res.edge_affinity[c].astype(float), 2))  # fmt: skip
    size = np.bincount(dp[dp >= 0], minlength=len(res.person_frame))
    first = np.searchsorted(res.person_frame, res.person_frame)
    for threshold in (0.05, 0.5):
        fast = criteria._agreements(rows, dp, size, first, threshold)
        plain = criteria._agreements(rows, dp, size, None, threshold)
        for x, y in zip(fast, plain, strict=True):
            np.testing.assert_array_equal(x, y)
        assert len(fast[0]) > (100 if threshold < 0.1 else 0)
