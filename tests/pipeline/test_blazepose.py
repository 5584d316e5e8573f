"""BlazePose detection: anchors, box decoding, NMS, rotated ROIs, joint-set maps, the
monocular 3D columns, resumable video detection, and the real models on rendered and
(if present) real frames.

Tests that run the models skip when no TFLite interpreter is installed (the ``[video]``
extra, ``pip install ai-edge-litert``); the rest are pure numpy/OpenCV.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.core.files import SceneFormatError
from pipeline.data.cameras import CameraRig, save_cameras
from pipeline.data.joint_sets import (
    BLAZEPOSE33,
    COCO17,
    SMPL24,
    blazepose33_to_smpl24_matrix,
    convert_keypoints,
)
from pipeline.data.scene import check_detections, load_scene
from pipeline.detect import blazepose as bp
from pipeline.detect import video as vid
from pipeline.run.frames import restored_joints
from pipeline.stages.restore import restore_mono_joints_2d, weak_perspective_project
from tests.pipeline.helpers import shelf_rig

REPO = Path(__file__).resolve().parents[2]
SHELF_SCENE = REPO / "sample_data" / "shelf_synth"
POSE2SIM_VIDEOS = REPO / "sample_data" / "pose2sim_demo" / "videos"


def _have_interpreter() -> bool:
    try:
        bp.load_interpreter_class()
    except bp.InterpreterMissingError:
        return False
    return True


needs_interpreter = pytest.mark.skipif(
    not _have_interpreter(),
    reason="no TFLite interpreter (pip install 'mvviz[video]' or ai-edge-litert)",
)


@pytest.fixture(scope="module")
def runner():
    if not _have_interpreter():
        pytest.skip("no TFLite interpreter (pip install 'mvviz[video]' or ai-edge-litert)")
    return bp.BlazePose(num_threads=2)


# --------------------------------------------------------------------------- anchors


def test_anchor_layout():
    a = bp.ssd_anchors()
    assert a.shape == (2254, 2)
    # stride 8: 28x28 cells x 2 anchors, row-major, two anchors per cell at one centre
    np.testing.assert_allclose(a[0], [0.5 / 28, 0.5 / 28])
    np.testing.assert_allclose(a[1], a[0])
    np.testing.assert_allclose(a[2], [1.5 / 28, 0.5 / 28])
    np.testing.assert_allclose(a[2 * 28], [0.5 / 28, 1.5 / 28])
    # stride 16: 14x14 x 2, then the three stride-32 layers merged: 7x7 x 6
    np.testing.assert_allclose(a[1568], [0.5 / 14, 0.5 / 14])
    np.testing.assert_allclose(a[1568 + 392 : 1568 + 392 + 6], np.tile([0.5 / 7, 0.5 / 7], (6, 1)))
    np.testing.assert_allclose(a[-1], [6.5 / 7, 6.5 / 7])
    assert ((a > 0) & (a < 1)).all()


@needs_interpreter
def test_anchor_count_matches_the_model(runner):
    shapes = [tuple(d["shape"]) for d in runner.detector.get_output_details()]
    assert (1, len(runner.anchors), 12) in shapes and (1, len(runner.anchors), 1) in shapes
    assert tuple(runner.detector.get_input_details()[0]["shape"]) == (1, 224, 224, 3)
    assert tuple(runner.landmarker.get_input_details()[0]["shape"]) == (1, 256, 256, 3)


# --------------------------------------------------------------------------- decoding, NMS


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_box_decoding_round_trips(seed):
    rng = np.random.default_rng(seed)
    anchors = bp.ssd_anchors()
    centre = rng.uniform(0, 1, (len(anchors), 2))
    size = rng.uniform(0.01, 0.5, (len(anchors), 2))
    boxes = np.concatenate([centre - size / 2, centre + size / 2], -1)
    keypoints = rng.uniform(-0.2, 1.2, (len(anchors), 4, 2))
    logits = rng.normal(0, 3, (len(anchors), 1))
    raw = bp.encode_detections(boxes, keypoints, anchors)
    b, k, s = bp.decode_detections(raw, logits, anchors)
    np.testing.assert_allclose(b, boxes, atol=1e-12)
    np.testing.assert_allclose(k, keypoints, atol=1e-12)
    np.testing.assert_allclose(s, 1 / (1 + np.exp(-logits[:, 0])))


def test_decoding_is_relative_to_the_anchor_in_input_pixels():
    anchors = np.array([[0.25, 0.75]])
    raw = np.zeros((1, 12))
    raw[0, :4] = [22.4, -22.4, 44.8, 22.4]  # centre +0.1, -0.1; size 0.2 x 0.1
    raw[0, 4:6] = [-11.2, 0.0]
    b, k, s = bp.decode_detections(raw, np.array([1000.0]), anchors)
    np.testing.assert_allclose(b[0], [0.25, 0.6, 0.45, 0.7])
    np.testing.assert_allclose(k[0, 0], [0.2, 0.75])
    np.testing.assert_allclose(k[0, 1], [0.25, 0.75])
    assert s[0] == pytest.approx(1.0)  # clipped logit, no overflow


def test_nms_merges_duplicates():
    boxes = np.array([[0.10, 0.10, 0.30, 0.30], [0.11, 0.10, 0.31, 0.30], [0.60, 0.60, 0.80, 0.80]])
    keypoints = np.array([[[0.2, 0.5]], [[0.22, 0.5]], [[0.7, 0.9]]])
    scores = np.array([0.6, 0.9, 0.8])
    b, k, s = bp.non_max_suppression(boxes, keypoints, scores, iou_threshold=0.3)
    assert len(s) == 2 and s.tolist() == [0.9, 0.8]
    w = np.array([0.9, 0.6]) / 1.5  # weighted by score, best first
    np.testing.assert_allclose(b[0], w @ boxes[[1, 0]])
    np.testing.assert_allclose(k[0, 0, 0], w @ [0.22, 0.2])
    np.testing.assert_allclose(b[1], boxes[2])
    b, k, s = bp.non_max_suppression(boxes, keypoints, scores, weighted=False)
    np.testing.assert_allclose(b[0], boxes[1])
    empty = bp.non_max_suppression(np.zeros((0, 4)), np.zeros((0, 4, 2)), np.zeros(0))
    assert [e.shape for e in empty] == [(0, 4), (0, 4, 2), (0,)]


def test_pose_nms_drops_the_duplicate_person():
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 500, (33, 2))
    kp = np.stack([a, a + 3.0, a + 200.0])
    keep = bp.pose_nms(kp, np.array([0.7, 0.9, 0.5]), np.full(3, 400.0))
    assert keep.tolist() == [1, 2]
    # a left/right-mirrored copy (a person seen from behind, read both ways)
    flip = BLAZEPOSE33.flip_index
    mirrored = np.stack([a, a[flip] + 2.0])
    assert bp.pose_nms(mirrored, np.array([0.9, 0.8]), np.full(2, 400.0)).tolist() == [0, 1]
    keep = bp.pose_nms(mirrored, np.array([0.9, 0.8]), np.full(2, 400.0), flip=flip)
    assert keep.tolist() == [0]
    # a garbled pose on the same hips
    garbled = np.stack([a, rng.uniform(0, 500, (33, 2))])
    garbled[1, bp.HIPS] = a[bp.HIPS] + 5.0
    assert bp.pose_nms(
        garbled, np.array([0.9, 0.8]), np.full(2, 400.0), centre=bp.HIPS
    ).tolist() == [0]


def test_letterbox_matrix_tracks_a_pixel():
    image = np.zeros((300, 600, 3), np.uint8)
    image[200:204, 450:454] = 255  # a bright 4x4 square centred at (451.5, 201.5)
    square, m = bp.letterbox(image, 224)
    assert square.shape == (224, 224, 3)
    ys, xs = np.nonzero(square[..., 0] > 40)
    w = square[ys, xs, 0].astype(float)
    found = np.array([w @ xs, w @ ys]) / w.sum()
    np.testing.assert_allclose(found, bp.apply_affine(m, np.array([451.5, 201.5])), atol=0.3)
    # the padding (top and bottom here) is black, the content centred
    assert square[:50].max() == 0 and square[-50:].max() == 0


def test_tiles_cover_the_image():
    w = bp.tile_windows(1032, 776, 2)
    assert len(w) == 4
    assert w[:, 0].min() == 0 and w[:, 2].max() == 1032 and w[:, 3].max() == 776
    assert (w[:, 2] - w[:, 0] == w[:, 3] - w[:, 1]).all()
    assert len(bp.tile_windows(1032, 776, 1)) == 0
    tall = bp.tile_windows(1088, 1920, 2)
    assert (tall[:, 2] - tall[:, 0] == 1088).all() and tall[:, 3].max() == 1920


# --------------------------------------------------------------------------- ROI


def test_roi_of_an_upright_person():
    kp = np.array([[[500.0, 600.0], [500.0, 200.0], [500.0, 300.0], [500.0, 100.0]]])
    rois = bp.alignment_rois(kp)
    np.testing.assert_allclose(rois.centre[0], [500, 600])
    assert rois.size[0] == pytest.approx(2 * 400 * 1.25)
    assert rois.angle[0] == pytest.approx(0.0)
    m = bp.roi_matrices(rois, 256)[0]
    # the crop's centre is the hip centre, its top edge is `size / 2` above it
    np.testing.assert_allclose(bp.apply_affine(m, np.array([127.5, 127.5])), [500, 600])
    np.testing.assert_allclose(bp.apply_affine(m, np.array([127.5, -0.5])), [500, 100])


@settings(max_examples=40, deadline=None)
@given(angle=st.floats(-3.1, 3.1), length=st.floats(50, 800))
def test_roi_rotation_puts_the_head_up(angle, length):
    """A person tilted by ``angle`` (clockwise on screen): the ROI's angle is that tilt,
    and the crop's up direction points from the hips to the full-body point."""
    hip = np.array([640.0, 360.0])
    head_dir = np.array([np.sin(angle), -np.cos(angle)])  # 0 = up (y down), pi/2 = right
    kp = np.stack([hip, hip + length * head_dir, hip, hip])[None]
    rois = bp.alignment_rois(kp, scale=1.0)
    assert np.cos(rois.angle[0] - angle) == pytest.approx(1.0)
    m = bp.roi_matrices(rois, 256)[0]
    top = bp.apply_affine(m, np.array([127.5, -0.5]))
    np.testing.assert_allclose(top, hip + length * head_dir, atol=1e-6)


def test_crop_of_a_tilted_person_is_upright():
    """Draw a 'person' lying with the head to the right; the crop shows it head up."""
    image = np.zeros((480, 640, 3), np.uint8)
    hip, head = np.array([200.0, 240.0]), np.array([400.0, 240.0])
    cv2.line(image, (200, 240), (400, 240), (255, 255, 255), 9)
    cv2.circle(image, (400, 240), 20, (255, 0, 0), -1)  # red head
    rois = bp.alignment_rois(np.stack([hip, head, hip, hip])[None], scale=1.0)
    assert rois.angle[0] == pytest.approx(np.pi / 2)
    crop = bp.crop_rois(image, rois, 256)[0]
    red = (crop[..., 0] > 128) & (crop[..., 2] < 64)
    ys, xs = np.nonzero(red)
    assert abs(xs.mean() - 127.5) < 2 and ys.mean() < 10  # head at the top centre
    white = (crop[..., 2] > 128).any(1)
    assert white[20:128].all()  # the body goes down from the head to the hips


def test_crop_pyramid_matches_direct_sampling():
    rng = np.random.default_rng(1)
    image = cv2.GaussianBlur(rng.integers(0, 255, (1600, 1600, 3), np.uint8), (0, 0), 12)
    rois = bp.Rois(centre=np.array([[800.0, 800.0]]), size=np.array([1400.0]), angle=np.zeros(1))
    direct = cv2.warpAffine(
        image,
        bp.roi_matrices(rois, 64)[0],
        (64, 64),
        flags=cv2.INTER_AREA | cv2.WARP_INVERSE_MAP,
    )
    crop = bp.crop_rois(image, rois, 64)[0]
    assert np.abs(crop.astype(float) - direct).mean() < 4.0


# --------------------------------------------------------------------------- joint sets


def test_blazepose_to_coco17_by_name():
    kp = np.zeros((33, 3))
    kp[:, 0] = np.arange(33)
    kp[:, 2] = 1.0
    coco = convert_keypoints(kp, BLAZEPOSE33, COCO17)
    expect = [0, 2, 5, 7, 8, 11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28]
    assert coco[:, 0].tolist() == expect
    assert (coco[:, 2] == 1).all()
    assert BLAZEPOSE33.names[2] == "left_eye" and BLAZEPOSE33.names[31] == "left_foot_index"
    flip = BLAZEPOSE33.flip_index
    assert flip[BLAZEPOSE33.index["left_heel"]] == BLAZEPOSE33.index["right_heel"]


def test_blazepose_to_smpl24_matrix():
    m = blazepose33_to_smpl24_matrix()
    idx = BLAZEPOSE33.index
    pelvis = m[SMPL24.index["pelvis"]]
    assert pelvis[idx["left_hip"]] == pelvis[idx["right_hip"]] == 0.5
    head = m[SMPL24.index["head"]]
    assert head[[idx["nose"], idx["left_ear"], idx["right_ear"]]] == pytest.approx([1 / 3] * 3)
    for name in ("spine1", "spine2", "spine3", "neck", "left_collar", "right_collar"):
        assert np.isnan(m[SMPL24.index[name]]).all()
    have = np.isfinite(m).all(1)
    np.testing.assert_allclose(m[have].sum(1), 1.0)
    assert have.sum() == 18
    world = np.random.default_rng(0).normal(0, 0.3, (2, 33, 3))
    mono = bp.mono_joints_smpl24(world)
    np.testing.assert_allclose(mono[:, SMPL24.index["left_knee"]], world[:, idx["left_knee"]])
    assert np.isnan(mono[:, SMPL24.index["neck"]]).all()


# --------------------------------------------------------------------------- mono 3D columns


def _synthetic_camera_poses(num_frames: int, seed: int = 0) -> vid.CameraPoses:
    """Rows whose 2D landmarks are the exact weak-perspective image of their 3D."""
    rng = np.random.default_rng(seed)
    world = rng.normal(0, 0.35, (num_frames, 33, 3))
    rois = np.column_stack(
        [rng.uniform(300, 700, (num_frames, 2)), rng.uniform(300, 500, num_frames)]
    )
    rois = np.column_stack([rois, np.zeros(num_frames)])
    bbox = bp.square_bbox(bp.Rois.from_array(rois))
    cam = np.column_stack([rng.uniform(0.8, 1.2, num_frames), rng.normal(0, 0.1, (num_frames, 2))])
    xy = weak_perspective_project(world, cam, bbox)
    kp = np.concatenate([xy, rng.uniform(0.5, 1.0, (num_frames, 33, 1))], -1)
    return vid.CameraPoses(
        frame=np.arange(num_frames),
        keypoints=kp,
        world=world,
        score=np.full(num_frames, 0.9),
        presence=np.ones(num_frames),
        rois=rois,
        done=np.arange(num_frames),
    )


def test_mono_columns_restore_onto_the_landmarks():
    poses = _synthetic_camera_poses(6)
    cols = vid.detection_columns(poses, view=1, scale=2.0)
    det = check_detections(cols, source="test", num_joints=17, num_views=5)
    assert det.mono_joints3d.shape == (6, 24, 3) and det.mono_valid.all() and not det.has_smpl
    restored = restore_mono_joints_2d(det.mono_joints3d, det.cam_weak, det.bbox)
    # projected mono joints land on the (scaled) 2D landmarks they were built from
    m = blazepose33_to_smpl24_matrix()
    have = np.isfinite(m).all(1)
    expect = np.einsum("sj,njc->nsc", m[have], 2.0 * poses.keypoints[..., :2])
    np.testing.assert_allclose(restored[:, have, :2], expect, atol=1e-6)
    assert (restored[:, ~have, 2] == 0).all() and (restored[:, have, 2] == 1).all()
    np.testing.assert_allclose(det.keypoints[:, 1, :2], 2.0 * poses.keypoints[:, 2, :2])


def test_check_detections_mono_columns():
    cols = vid.detection_columns(_synthetic_camera_poses(3), view=0, scale=1.0)
    arrays = {k: cols[k] for k in ("frame", "view", "keypoints", "mono_joints3d", "bbox")}
    with pytest.raises(SceneFormatError, match="cam_weak"):
        check_detections(arrays, source="t", num_joints=17, num_views=1)
    bad = dict(cols, mono_joints3d=cols["mono_joints3d"][:, :17])
    with pytest.raises(SceneFormatError, match=r"mono_joints3d.*expected shape"):
        check_detections(bad, source="t", num_joints=17, num_views=1)
    nan_cam = dict(cols, cam_weak=np.full((3, 3), np.nan))
    with pytest.raises(SceneFormatError, match="cam_weak"):
        check_detections(nan_cam, source="t", num_joints=17, num_views=1)
    lone = {k: cols[k] for k in ("frame", "view", "keypoints", "cam_weak", "bbox")}
    with pytest.raises(SceneFormatError, match="need smpl_pose"):
        check_detections(lone, source="t", num_joints=17, num_views=1)


# --------------------------------------------------------------------------- videos


def _write_video(path: Path, num_frames: int, size=(96, 64), fps: float = 10.0) -> None:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
    for i in range(num_frames):
        frame = np.full((size[1], size[0], 3), 0, np.uint8)
        cv2.putText(frame, str(i), (5, 50), cv2.FONT_HERSHEY_SIMPLEX, 1.5, (255, 255, 255), 3)
        w.write(frame)
    w.release()


class FakeDetector:
    """Stands in for BlazePose: one person per frame, landmarks from the frame index."""

    def __init__(self, fail_after: int | None = None) -> None:
        self.calls = 0
        self.fail_after = fail_after

    def __call__(self, image: np.ndarray) -> bp.Poses:
        if self.fail_after is not None and self.calls >= self.fail_after:
            raise KeyboardInterrupt
        self.calls += 1
        poses = _synthetic_camera_poses(1, seed=self.calls)
        return bp.Poses(
            keypoints=poses.keypoints * [0.1, 0.1, 1.0],
            world=poses.world,
            score=poses.score,
            presence=poses.presence,
            rois=bp.Rois.from_array(poses.rois * [0.1, 0.1, 0.1, 1.0]),
        )


def test_match_videos_and_sizes(tmp_path):
    for name in ("cam1.mp4", "cam2.avi", "extra.mp4", "notes.txt"):
        (tmp_path / name).write_bytes(b"")
    found = vid.find_videos([tmp_path])
    assert [p.name for p in found] == ["cam1.mp4", "cam2.avi", "extra.mp4"]
    m = vid.match_videos(["cam1", "cam2", "cam3"], found)
    assert set(m.videos) == {"cam1", "cam2"} and m.missing_cameras == ["cam3"]
    assert [p.name for p in m.unmatched_videos] == ["extra.mp4"]
    info = vid.VideoInfo(path=tmp_path / "cam1.mp4", num_frames=1, fps=25, width=960, height=540)
    assert vid.image_scale(info, 1920, 1080) == 2.0
    with pytest.raises(ValueError, match="not a uniform scale"):
        vid.image_scale(info, 1920, 1920)


def test_iter_frames_every(tmp_path):
    _write_video(tmp_path / "a.mp4", 9)
    info = vid.probe_video(tmp_path / "a.mp4")
    assert (info.num_frames, info.width, info.height) == (9, 96, 64)
    assert [i for i, _ in vid.iter_frames(info.path, start=1, step=3)] == [1, 4, 7]
    assert [i for i, _ in vid.iter_frames(info.path, stop=20, step=4)] == [0, 4, 8]


def _tiny_scene(tmp_path: Path, counts: dict[str, int]) -> tuple[Path, Path]:
    shelf = shelf_rig()
    rig = CameraRig(tuple(replace(shelf[i], name=n) for i, n in enumerate(counts)))
    scene = tmp_path / "scene"
    scene.mkdir()
    save_cameras(rig, scene / "cameras.json")
    videos = tmp_path / "videos"
    videos.mkdir()
    for cam, n in counts.items():
        c = rig[rig.index_of(cam)]
        _write_video(videos / f"{cam}.mp4", n, size=(c.width // 4, c.height // 4))
    return scene, videos


def test_detect_scene_resumes_and_reports_lengths(tmp_path, monkeypatch):
    monkeypatch.setattr(vid, "CACHE_EVERY", 2)
    scene, videos = _tiny_scene(tmp_path, {"a": 7, "b": 6})
    logs: list[str] = []
    # interrupted after 5 frames of camera a: its cache holds the first 4
    with pytest.raises(KeyboardInterrupt):
        vid.detect_scene(scene, [videos], progress=False, log=logs.append, detector=FakeDetector(5))
    assert not (scene / "detections.npz").exists()
    assert (scene / ".mvviz" / "detect" / "a.npz").is_file()
    assert any("frame counts differ" in m and "6 frames" in m for m in logs)
    fake = FakeDetector()
    logs.clear()
    report = vid.detect_scene(scene, [videos], progress=False, log=logs.append, detector=fake)
    assert fake.calls == (6 - 4) + 6  # camera a resumed at frame 4, camera b from scratch
    assert any("resuming, 4 frames cached" in m for m in logs)
    assert report.num_frames == 6 and report.rows_per_camera == {"a": 6, "b": 6}
    s = load_scene(scene)
    assert s.num_frames == 6 and s.joint_set.name == "coco17" and s.fps == 10.0
    assert s.detections.mono_joints3d is not None and s.detections.mono_valid.all()
    restored = restored_joints(s, model=None)  # no SMPL rows: the body model is not needed
    assert restored.shape == (12, 24, 3)
    assert (restored[:, SMPL24.index["neck"], 2] == 0).all()
    assert (restored[:, SMPL24.index["left_knee"], 2] > 0).all()
    sub = s.detections.take(np.array([0, 3]))
    np.testing.assert_array_equal(sub.mono_joints3d, s.detections.mono_joints3d[[0, 3]])
    assert set(s.videos) == {"a", "b"}
    meta = json.loads((scene / "scene.json").read_text())
    assert meta["detect"]["video_frames"] == {"a": 7, "b": 6}
    # keypoints are in calibration pixels: the videos are quarter size
    cam_a = s.rig[s.rig.index_of("a")]
    assert s.detections.keypoints[..., 0].max() > cam_a.width / 4
    # a rerun refuses to replace detections.npz, and with --overwrite uses the cache only
    with pytest.raises(FileExistsError):
        vid.detect_scene(scene, [videos], progress=False, log=logs.append, detector=fake)
    again = FakeDetector()
    vid.detect_scene(
        scene, [videos], overwrite=True, progress=False, log=logs.append, detector=again
    )
    assert again.calls == 0


def test_detect_fills_an_empty_detections_file(tmp_path):
    """A scene converted from a calibration alone has a detections file with no rows:
    detect fills it without --overwrite; a file with detections still needs it."""
    scene, videos = _tiny_scene(tmp_path, {"a": 4})
    empty = {"frame": np.zeros(0, np.int64), "view": np.zeros(0, np.int64),
             "keypoints": np.zeros((0, 17, 3), np.float32)}  # fmt: skip
    np.savez(scene / "detections.npz", **empty)
    report = vid.detect_scene(
        scene, [videos], progress=False, log=lambda m: None, detector=FakeDetector()
    )
    assert report.rows_per_camera == {"a": 4}
    assert len(load_scene(scene).detections) == 4
    with pytest.raises(FileExistsError):
        vid.detect_scene(scene, [videos], progress=False, log=lambda m: None,
                         detector=FakeDetector())  # fmt: skip


def test_detect_scene_every_reencodes_videos(tmp_path):
    scene, videos = _tiny_scene(tmp_path, {"a": 9})
    report = vid.detect_scene(
        scene,
        [videos / "a.mp4"],
        settings=vid.DetectSettings(every=4),
        progress=False,
        log=lambda m: None,
        detector=FakeDetector(),
    )
    assert report.num_frames == 3 and report.fps == pytest.approx(2.5)
    assert vid.probe_video(scene / "videos" / "a.mp4").num_frames == 3


# --------------------------------------------------------------------------- real models


def _shelf_frame(view: int, frame: int) -> np.ndarray:
    cap = cv2.VideoCapture(str(SHELF_SCENE / "videos" / f"{view}.mp4"))
    cap.set(cv2.CAP_PROP_POS_FRAMES, frame)
    ok, bgr = cap.read()
    cap.release()
    assert ok
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


@pytest.mark.slow
@pytest.mark.skipif(not (SHELF_SCENE / "videos").is_dir(), reason="no shipped Shelf renders")
def test_detector_on_synthetic_renders(runner):
    """The shipped Shelf scene's renders (the project's renderer: untextured, shaded
    bodies). Measured at frame 0 of the 5 views (tiles=2): 11 of the 17 people who are
    80 % inside a view are found with keypoints within 5 % of their height (median
    error about 2 %); misses are people seen from behind, small or cut by the border.
    Asserted: at least half found, accurately, and no ghost far from every person."""
    scene = load_scene(SHELF_SCENE)
    found, visible, errors = 0, 0, []
    for v, cam in enumerate(scene.rig):
        poses = runner(_shelf_frame(v, 0))
        coco = convert_keypoints(poses.keypoints, BLAZEPOSE33, COCO17)
        truth = [scene.gt.keypoints3d[i] for i in np.flatnonzero(scene.gt.frame == 0)]
        uv_all = [cam.project(k) for k in truth]
        for uv, k in zip(uv_all, truth, strict=True):
            inside = (uv[:, 0] > 0) & (uv[:, 0] < cam.width) & (uv[:, 1] > 0)
            inside &= (uv[:, 1] < cam.height) & (cam.world_to_camera(k)[:, 2] > 0)
            if inside.mean() < 0.8:
                continue
            visible += 1
            height = np.ptp(uv[:, 1])
            d = [np.median(np.linalg.norm(c[:, :2] - uv, axis=1)) / height for c in coco]
            if d and min(d) < 0.05:
                found += 1
                errors.append(min(d))
        for c in coco:  # every detection is near some (possibly mostly hidden) person
            near = [np.median(np.linalg.norm(c[:, :2] - uv, axis=1)) for uv in uv_all]
            assert min(near) < 0.5 * max(np.ptp(uv[:, 1]) for uv in uv_all)
        assert np.isfinite(poses.world).all() and (np.abs(poses.world) < 1.5).all()
    print(f"\nshelf renders, frame 0: {found} of {visible} visible people found")
    assert found >= visible / 2
    assert np.median(errors) < 0.03


@pytest.mark.skipif(not POSE2SIM_VIDEOS.is_dir(), reason="no pose2sim demo clip shipped yet")
def test_detector_on_pose2sim_demo(runner):
    """Real video: the first frame of each camera of the pose2sim multi-person demo."""
    counts = {}
    for path in sorted(POSE2SIM_VIDEOS.glob("*.mp4")):
        _, image = next(vid.iter_frames(path))
        counts[path.stem] = len(runner(image))
    print(f"\npose2sim demo, frame 0, people per view: {counts}")
    assert counts and all(n >= 1 for n in counts.values())


@pytest.mark.slow
@needs_interpreter
def test_cli_detect_on_frames_without_people(tmp_path, capsys):
    from mvviz.cli import main

    scene, videos = _tiny_scene(tmp_path, {"a": 3, "b": 3})
    assert main(["detect", str(scene), "--videos", str(videos), "--no-progress"]) == 0
    s = load_scene(scene)
    assert len(s.detections) == 0 and s.num_frames == 3
    assert s.detections.mono_joints3d.shape == (0, 24, 3)
    assert "0 people in 0 of 3 frames" in capsys.readouterr().out
    (tmp_path / "other").mkdir()
    _write_video(tmp_path / "other" / "nobody.mp4", 2)
    code = main(["detect", str(scene), "--videos", str(tmp_path / "other"), "--overwrite"])
    assert code == 2
    assert "no video is named after a camera" in capsys.readouterr().err
