"""The floor a body fit is judged by: the best skeleton of constant bone lengths."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.data.joint_sets import get_joint_set
from pipeline.fit.floor import rigid_floor, spanning_tree

COCO = get_joint_set("coco17")
BONES = np.array(COCO.bones)


def walking_skeleton(frames: int, lengths: np.ndarray, seed: int = 0) -> np.ndarray:
    """(1, F, 17, 3) mm: a skeleton of the given bone lengths whose bones turn smoothly."""
    parent, pairs = spanning_tree(BONES, COCO.num_joints)
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 2 * np.pi, (len(pairs), 2))
    out = np.zeros((1, frames, COCO.num_joints, 3))
    for f in range(frames):
        for r in np.flatnonzero(parent < 0):
            out[0, f, r] = (10.0 * f, 0.0, 1000.0 + 500.0 * r)
        for b, (p, c) in enumerate(pairs):
            a, e = 0.05 * f + phase[b]
            d = np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])
            out[0, f, c] = out[0, f, p] + lengths[f, b] * d
    return out


def test_spanning_tree_covers_every_joint_once():
    parent, pairs = spanning_tree(BONES, COCO.num_joints)
    # COCO's bones are two pieces, the body (rooted at a shoulder: 3 bones) and the face
    # (at the nose): two roots, 15 bones, every other joint a child once
    roots = np.flatnonzero(parent < 0)
    assert len(roots) == 2 and len(pairs) == COCO.num_joints - 2
    assert sorted(pairs[:, 1].tolist()) == sorted(set(range(17)) - set(roots.tolist()))
    assert (parent[pairs[:, 1]] == pairs[:, 0]).all()
    names = {COCO.names[r] for r in roots}
    assert "nose" in names and names & {"left_shoulder", "right_shoulder"}


def test_a_rigid_skeleton_is_its_own_floor():
    rng = np.random.default_rng(1)
    lengths = np.tile(rng.uniform(80, 400, 15), (60, 1))
    x = walking_skeleton(60, lengths)
    floor = rigid_floor(x, BONES)
    assert floor.median()[0] < 0.5  # mm
    np.testing.assert_allclose(np.sort(floor.bone_lengths[0]), np.sort(lengths[0]), atol=1.0)


def test_a_bone_that_changes_length_is_what_is_left():
    """One leaf bone 20 mm longer and shorter in turn: no constant length follows it; the
    least-squares answer splits the 20 mm between the leaf and its parent (10 + 10)."""
    rng = np.random.default_rng(2)
    lengths = np.tile(rng.uniform(150, 400, 15), (80, 1))
    parent, pairs = spanning_tree(BONES, COCO.num_joints)
    leaf = [b for b, (p, c) in enumerate(pairs) if c not in pairs[:, 0]][0]
    swing = 20.0 * np.sign(np.sin(np.arange(80) * 0.5))
    lengths[:, leaf] += swing
    x = walking_skeleton(80, lengths, seed=3)
    floor = rigid_floor(x, BONES)
    p, c = pairs[leaf]
    err = np.linalg.norm(floor.joints[0, :, [p, c]] - x[0, :, [p, c]], axis=-1)  # (2, F)
    assert 7.0 < np.median(err[1]) < 13.0 and 7.0 < np.median(err[0]) < 13.0
    assert abs(np.median(err.sum(0)) - 20.0) < 3.0
    assert 0.8 < floor.median()[0] < 2.0  # ~20 mm over 17 joints
    assert abs(floor.bone_lengths[0, leaf] - (lengths[:, leaf].mean())) < 5.0


def test_missing_joints_frames_and_tracks():
    rng = np.random.default_rng(4)
    lengths = np.tile(rng.uniform(80, 400, 15), (40, 1))
    one = walking_skeleton(40, lengths)
    x = np.concatenate([one, np.full_like(one, np.nan)])  # a second track never seen
    x[0, 10:15] = np.nan  # frames without the person
    x[0, ::4, 9] = np.nan  # a joint missing now and then
    floor = rigid_floor(x, BONES)
    assert np.isnan(floor.distance[1]).all() and np.isnan(floor.median()[1])
    assert np.isnan(floor.distance[0, 10:15]).all()
    assert np.isfinite(floor.joints[0, 20]).all()  # the missing joint placed all the same
    assert floor.median()[0] < 1.0
    empty = rigid_floor(np.full((0, 5, 17, 3), np.nan), BONES)
    assert empty.distance.shape == (0, 5)


@pytest.mark.slow
def test_eval_reports_fits_against_the_floor(tmp_path):
    """A run's fits and its floor, per track and in all, in the evaluation. On the sample
    step I is at the floor: its keypoints are the body model's own, regressed from the
    skinned surface, so their distances change a little with the pose and a body can
    land under a rigid stick skeleton (measured floor / step I 4.1 / 3.4, 3.9 / 3.1,
    4.6 / 4.4, 5.7 / 4.3 mm)."""
    from pipeline.body.model import load_body_model
    from pipeline.config import PipelineConfig
    from pipeline.data.scene import load_scene
    from pipeline.evaluation.evaluate import evaluate, format_table
    from pipeline.run.pipeline import run_pipeline
    from tests.conftest import REPO

    scene = load_scene(REPO / "sample_data" / "shelf_synth")
    res = run_pipeline(scene, PipelineConfig(), load_body_model(), progress=False)
    assert res.fit_floor.shape == (res.num_tracks, res.num_frames)
    ev = evaluate(scene, res)
    d = ev.fit_distance
    assert set(d) == {str(k) for k in range(res.num_tracks)} | {"all"}
    for row in d.values():
        assert 2.0 < row["floor"] < 10.0
        assert abs(row["smpl"] - row["floor"]) < 2.0 and abs(row["smpl_vae"] - row["floor"]) < 2.0
    assert "floor mm" in format_table(ev) and ev.to_json()["fit_distance_mm"] == d
    no_floor = run_pipeline(
        scene, PipelineConfig().with_overrides(["smpl_fit.floor_iterations=0"]),
        load_body_model(), progress=False,
    )  # fmt: skip
    assert (
        no_floor.fit_floor is None and "floor" not in evaluate(scene, no_floor).fit_distance["all"]
    )
