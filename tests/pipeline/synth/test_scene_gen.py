"""Synthetic scenes: determinism, ground truth agrees with the renders, detector noise."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from pipeline.body.model import load_body_model
from pipeline.data.joint_sets import SMPL24
from pipeline.data.scene import load_scene
from pipeline.importers.calibration import read_voxelpose_calibration
from pipeline.synth.scene_gen import (
    PERSON_COLOURS,
    SynthConfig,
    visible_floor_area,
    write_synth_scene,
)
from tests.conftest import REPO

RIG = REPO / "sample_data" / "rigs" / "campus_voxelpose.json"


@pytest.fixture(scope="module")
def campus_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "campus"
    rig = read_voxelpose_calibration(RIG)
    write_synth_scene(
        out,
        rig,
        load_body_model(),
        SynthConfig(num_people=2, num_frames=12, seed=3),
        progress=False,
    )
    return load_scene(out)


@pytest.mark.slow
def test_scene_loads_with_all_parts(campus_scene):
    s = campus_scene
    assert len(s.rig) == 3 and s.num_frames == 12
    assert s.gt is not None and s.gt.joints3d.shape == (24, 24, 3)
    assert set(s.videos) == {"0", "1", "2"}
    assert s.detections.has_smpl and s.detections.gt_person_id is not None
    cap = cv2.VideoCapture(str(s.videos["0"]))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 12


def test_feet_on_floor_and_people_apart(campus_scene):
    j = campus_scene.gt.joints3d.reshape(2, 12, 24, 3)
    feet = j[:, :, [SMPL24.index["left_foot"], SMPL24.index["right_foot"]], 2]
    # The lowest vertex touches z = 0; foot joints sit a few cm above it.
    assert 0 < feet.min() < 120
    pelvis = j[:, :, 0, :2]
    assert np.linalg.norm(pelvis[0] - pelvis[1], axis=-1).min() >= 650


def test_ground_truth_lands_on_rendered_bodies(campus_scene):
    # Project mid-body joints of each person into every view; where the joint is in the
    # image and not hidden, the video pixel must be that person's colour, not background.
    s = campus_scene
    hits = 0
    for cam in s.rig:
        cap = cv2.VideoCapture(str(s.videos[cam.name]))
        cap.set(cv2.CAP_PROP_POS_FRAMES, 6)
        ok, bgr = cap.read()
        assert ok
        rgb = bgr[..., ::-1].astype(float)
        for p in range(2):
            g = s.gt.joints3d[(s.gt.frame == 6) & (s.gt.person_id == p)][0]
            for name in ("spine2", "spine3", "pelvis"):
                u, w = np.round(cam.project(g[SMPL24.index[name]])).astype(int)
                if not (0 <= u < cam.width and 0 <= w < cam.height):
                    continue
                colour = np.array(PERSON_COLOURS[p], float)
                patch = rgb[max(w - 1, 0) : w + 2, max(u - 1, 0) : u + 2].reshape(-1, 3)
                # Shaded colour: a multiple of the albedo, so its direction matches.
                cos = patch @ colour / (np.linalg.norm(patch, axis=1) * np.linalg.norm(colour))
                other = [np.array(c, float) for q, c in enumerate(PERSON_COLOURS[:2]) if q != p]
                cos_other = (
                    patch @ other[0] / (np.linalg.norm(patch, axis=1) * np.linalg.norm(other[0]))
                )
                if cos.mean() > cos_other.mean():
                    hits += 1
    # Some joints may be hidden behind the other person; most must land on their body.
    assert hits >= 8


def test_keypoints_are_near_the_truth(campus_scene):
    s = campus_scene
    d = s.detections
    real = d.gt_person_id >= 0
    assert real.sum() > 30 and (d.gt_person_id == -1).sum() >= 0
    # Restored SMPL joints vs projected truth: the weak-perspective fit + pose noise
    # keeps them within tens of pixels (Campus people are ~120 px tall).
    from pipeline.stages.restore import restore_joints_2d

    r = restore_joints_2d(d.smpl_pose, d.smpl_betas, d.cam_weak, d.bbox, load_body_model())
    errs = []
    for i in np.flatnonzero(real):
        g = s.gt.joints3d[(s.gt.frame == d.frame[i]) & (s.gt.person_id == d.gt_person_id[i])][0]
        errs.append(np.linalg.norm(r[i, :, :2] - s.rig[d.view[i]].project(g), axis=-1))
    assert np.median(errs) < 15


@pytest.mark.slow
def test_deterministic_for_a_seed(tmp_path):
    rig = read_voxelpose_calibration(RIG)
    cfg = SynthConfig(num_people=1, num_frames=4, seed=11, render_video=False)
    model = load_body_model()
    a = write_synth_scene(tmp_path / "a", rig, model, cfg, progress=False)
    b = write_synth_scene(tmp_path / "b", rig, model, cfg, progress=False)
    da, db = load_scene(a).detections, load_scene(b).detections
    np.testing.assert_array_equal(da.keypoints, db.keypoints)
    np.testing.assert_array_equal(da.smpl_pose, db.smpl_pose)


def test_visible_area_is_inside_the_rig():
    rig = read_voxelpose_calibration(REPO / "sample_data" / "rigs" / "shelf_voxelpose.json")
    area = visible_floor_area(rig)
    assert len(area) > 100
    # Every point is seen (feet to head) by at least two cameras.
    for x, y in area[:: max(1, len(area) // 20)]:
        seen = 0
        for cam in rig:
            uv = cam.project(np.array([[x, y, 0.0], [x, y, 1700.0]]))
            seen += bool(
                np.isfinite(uv).all()
                and (uv[:, 0] >= 0).all() and (uv[:, 0] < cam.width).all()
                and (uv[:, 1] >= 0).all() and (uv[:, 1] < cam.height).all()
            )  # fmt: skip
        assert seen >= 2


@pytest.mark.slow
@pytest.mark.parametrize("occlusion", ["proxy", "render"])
def test_detections_streamed_to_columns_equal_those_kept_in_memory(
    tmp_path, monkeypatch, occlusion
):
    """A long synthesis streams its detection rows to a directory of .npy columns a block
    at a time (flushed here every 5 rows, so many blocks): the scene it writes reads back
    array for array as the one whose rows were kept in memory and written as one file."""
    from pipeline.synth import detection_rows

    monkeypatch.setattr(detection_rows, "FLUSH_ROWS", 5)
    rig, model = read_voxelpose_calibration(RIG), load_body_model()
    cfg = SynthConfig(num_people=3, num_frames=8, seed=5, render_video=False, occlusion=occlusion)
    a = write_synth_scene(tmp_path / "a", rig, model, cfg, progress=False,
                          detections_file="detections.npz")  # fmt: skip
    b = write_synth_scene(tmp_path / "b", rig, model, cfg, progress=False,
                          detections_file="detections")  # fmt: skip
    assert (a / "detections.npz").is_file() and (b / "detections" / "keypoints.npy").is_file()
    assert not list(tmp_path.glob(".*"))  # no temporary directory left
    da, db = load_scene(a).detections, load_scene(b).detections
    assert len(da) > 5 * 5  # several blocks
    for k, x in da.arrays().items():
        y = db.arrays()[k]
        assert y.dtype == x.dtype and y.shape == x.shape, k
        np.testing.assert_array_equal(y, x, err_msg=k)
    np.testing.assert_array_equal(load_scene(a).gt.joints3d, load_scene(b).gt.joints3d)


def test_long_syntheses_stream_and_an_empty_one_writes_empty_columns(tmp_path, monkeypatch):
    """Without a choice, scenes of STREAM_VIEW_FRAMES view-frames or more get a detections
    directory, shorter ones one file; streamed rows of which there are none close as
    columns of 0 rows with the dtypes and widths of the in-memory ones."""
    import pipeline.synth.scene_gen as scene_gen

    monkeypatch.setattr(scene_gen, "STREAM_VIEW_FRAMES", 3 * 6)
    rig, model = read_voxelpose_calibration(RIG), load_body_model()
    cfg = SynthConfig(num_people=1, num_frames=6, seed=2, render_video=False, occlusion="proxy")
    out = write_synth_scene(tmp_path / "long", rig, model, cfg, progress=False)
    assert (out / "detections").is_dir() and len(load_scene(out).detections) > 0
    short = write_synth_scene(tmp_path / "short", rig, model,
                              SynthConfig(num_people=1, num_frames=5, seed=2, render_video=False,
                                          occlusion="proxy"), progress=False)  # fmt: skip
    assert (short / "detections.npz").is_file()
    rows = scene_gen.DetectionRows(17, tmp_path / "empty")
    empty = rows.detections()
    assert len(empty) == 0 and empty.keypoints.shape == (0, 17, 3)
    assert empty.smpl_pose.shape == (0, 72) and empty.frame.dtype == np.int64
