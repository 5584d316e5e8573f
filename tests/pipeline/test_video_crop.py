"""Videos that do not match the calibration to the pixel (pipeline/detect/video_crop.py): the size
rule, the pixel mapping, frames placed on the calibrated image, and the mapping applied
where video pixels become detections (mvviz detect) and where the viewer shows frames."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

import pipeline.detect.blazepose as bp
import pipeline.detect.video as vid
from mvviz.cli import main
from mvviz.scene.images import FrameStore
from pipeline.data.cameras import Camera, CameraRig, save_cameras
from pipeline.data.scene import load_scene
from pipeline.detect.video_crop import (
    FILL,
    CalibratedFrames,
    VideoSizeError,
    parse_video_crops,
    resolve_video_crop,
    to_calibrated_frame,
)

P2S_VIDEOS = Path("/work/shared/data/pose2sim_balancing/videos")


# --------------------------------------------------------------------------- the rule


@pytest.mark.parametrize(
    ("video", "calib", "rule", "scale", "crop"),
    [
        ((1080, 1920), (1088, 1920), "encoder", 1.0, (0, 0, 8, 0)),  # Pose2Sim cams 1-2
        ((1088, 1920), (1088, 1920), "exact", 1.0, (0, 0, 0, 0)),  # cams 3-4
        ((544, 960), (1088, 1920), "scale", 2.0, (0, 0, 0, 0)),
        ((540, 960), (1088, 1920), "encoder", 2.0, (0, 0, 8, 0)),  # scaled, then cropped
        ((1920, 1088), (1920, 1080), "encoder", 1.0, (0, 0, 0, -8)),  # padded to 16 px
        ((3816, 2160), (3840, 2160), "encoder", 1.0, (0, 0, 24, 0)),  # 24 px < 1 % of 3816
        ((1920, 1080), (1920, 1081), "exact", 1.0, (0, 0, 0, 0)),  # within a pixel
    ],
)
def test_size_rule(video, calib, rule, scale, crop):
    vc = resolve_video_crop("cam01", video, calib)
    assert (vc.rule, vc.scale, vc.crop) == (rule, pytest.approx(scale), crop)
    # right/bottom crops move nothing: video pixel (0, 0) is calibrated pixel (0, 0)
    np.testing.assert_allclose(vc.offset, [0, 0])
    np.testing.assert_allclose(vc.to_calibrated([[10.0, 20.0]]), [[10 * scale, 20 * scale]])


def test_the_warning_states_the_rule():
    text = resolve_video_crop("cam01", (1080, 1920), (1088, 1920)).describe()
    assert "camera cam01: video 1080x1920, calibration 1088x1920" in text
    assert "cropped 8 px at the right" in text
    assert "principal point shift (+0, +0) px" in text
    assert "--video-crop cam01=LEFT,TOP,RIGHT,BOTTOM" in text


@pytest.mark.parametrize(
    ("video", "calib"),
    [
        ((1000, 1920), (1088, 1920)),  # 88 px: no encoder does that
        ((1068, 1920), (1088, 1920)),  # 20 px > 16 px and > 1 %
        ((3796, 2160), (3840, 2160)),  # 44 px > 1 % of 3796
        ((1080, 1910), (1088, 1920)),  # both dimensions off
        ((1920, 1080), (1080, 1920)),  # rotated
    ],
)
def test_anything_else_is_a_clear_error(video, calib):
    with pytest.raises(VideoSizeError) as err:
        resolve_video_crop("cam02", video, calib)
    msg = str(err.value)
    assert "camera cam02" in msg
    assert f"{video[0]}x{video[1]}" in msg and f"{calib[0]}x{calib[1]}" in msg
    assert "--video-crop cam02=LEFT,TOP,RIGHT,BOTTOM" in msg


def test_a_stated_crop():
    vc = resolve_video_crop("c", (1080, 1920), (1088, 1920), crop=(4, 0, 4, 0))
    assert vc.rule == "stated" and vc.scale == 1.0
    np.testing.assert_allclose(vc.to_calibrated([[0.0, 0.0], [1079, 1919]]), [[4, 0], [1083, 1919]])
    np.testing.assert_allclose(vc.to_video(vc.to_calibrated([[12.5, 7.0]])), [[12.5, 7.0]])
    assert "principal point shift (-4, +0) px" in vc.describe()
    half = resolve_video_crop("c", (540, 960), (1088, 1920), crop=(8, 0, 0, 0))
    assert half.scale == 2.0
    np.testing.assert_allclose(half.to_calibrated([[10.0, 10.0]]), [[28.0, 20.0]])
    with pytest.raises(VideoSizeError, match="leaves 1078x1920"):
        resolve_video_crop("c", (1080, 1920), (1088, 1920), crop=(5, 0, 5, 0))


def test_parse_video_crops():
    assert parse_video_crops(["cam01=0,0,8,0", "cam02=1.5,2,3,4"]) == {
        "cam01": (0, 0, 8, 0),
        "cam02": (1.5, 2, 3, 4),
    }
    for bad in (["cam01"], ["cam01=1,2,3"], ["=1,2,3,4"], ["c=a,b,c,d"]):
        with pytest.raises(ValueError, match="CAM=LEFT,TOP,RIGHT,BOTTOM"):
            parse_video_crops(bad)
    with pytest.raises(ValueError, match="twice"):
        parse_video_crops(["c=0,0,0,0", "c=0,0,1,0"])


def test_frames_are_placed_on_the_calibrated_image():
    img = np.random.default_rng(0).integers(0, 255, (64, 88, 3), np.uint8)
    out = to_calibrated_frame(img, resolve_video_crop("c", (88, 64), (96, 64)))
    assert out.shape == (64, 96, 3)
    np.testing.assert_array_equal(out[:, :88], img)
    assert (out[:, 88:] == FILL).all()
    padded = to_calibrated_frame(img, resolve_video_crop("c", (88, 64), (80, 64)))
    np.testing.assert_array_equal(padded, img[:, :80])  # the encoder's extra columns cut
    stated = to_calibrated_frame(
        img, resolve_video_crop("c", (88, 64), (96, 64), crop=(6, 0, 2, 0))
    )
    np.testing.assert_array_equal(stated[:, 6:94], img)
    assert (stated[:, :6] == FILL).all() and (stated[:, 94:] == FILL).all()
    half = to_calibrated_frame(img[::2, ::2], resolve_video_crop("c", (44, 32), (96, 64)))
    assert half.shape == (32, 48, 3)  # the calibrated image at the video's scale
    same = np.zeros((32, 48, 3), np.uint8)
    assert to_calibrated_frame(same, resolve_video_crop("c", (48, 32), (96, 64))) is same
    notes = []
    place = CalibratedFrames("c", (96, 64), note=notes.append)
    assert place(img).shape == (64, 96, 3) and place(img[:, :40]).shape == (64, 40, 3)
    assert len(notes) == 2 and "cropped 8 px at the right" in notes[0]
    assert "shown as they are" in notes[1]


@pytest.mark.skipif(not P2S_VIDEOS.is_dir(), reason="Pose2Sim balancing videos not present")
def test_pose2sim_balancing_videos():
    """The real case: cameras 1-2 encoded 8 px narrower than calibrated, 3-4 not."""
    rules = {}
    for cam in ("cam01", "cam02", "cam03", "cam04"):
        info = vid.probe_video(P2S_VIDEOS / f"{cam}.mp4")
        vc = vid.video_crop(cam, info, 1088, 1920)
        rules[cam] = (vc.rule, vc.crop)
    assert rules == {
        "cam01": ("encoder", (0, 0, 8, 0)),
        "cam02": ("encoder", (0, 0, 8, 0)),
        "cam03": ("exact", (0, 0, 0, 0)),
        "cam04": ("exact", (0, 0, 0, 0)),
    }


# --------------------------------------------------------------------------- detect + viewer


def _write_video(path: Path, size: tuple[int, int], num_frames: int = 3) -> None:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, size)
    for _ in range(num_frames):
        frame = np.full((size[1], size[0], 3), 200, np.uint8)
        frame[:, :4] = (0, 0, 255)  # a red stripe at the video's left edge
        w.write(frame)
    w.release()


class PointDetector:
    """One person whose 33 landmarks all sit at video pixel UV, whatever the image."""

    UV = np.array([20.0, 30.0])

    def __call__(self, image: np.ndarray) -> bp.Poses:
        world = np.random.default_rng(0).normal(0, 0.3, (1, 33, 3))
        kp = np.concatenate([np.broadcast_to(self.UV, (1, 33, 2)), np.full((1, 33, 1), 0.9)], -1)
        kp = kp + np.random.default_rng(1).normal(0, 2, kp.shape) * [1, 1, 0]
        rois = bp.Rois.from_array(np.array([[self.UV[0], self.UV[1], 40.0, 0.0]]))
        return bp.Poses(keypoints=kp, world=world, score=np.ones(1), presence=np.ones(1), rois=rois)


def _scene(tmp_path: Path, videos: dict[str, tuple[int, int]]) -> tuple[Path, Path]:
    K = np.array([[80.0, 0, 48], [0, 80, 32], [0, 0, 1]])
    cams = [
        Camera(n, 96, 64, K, np.zeros(5), np.eye(3), np.array([300.0 * i, 0, 3000]))
        for i, n in enumerate(videos)
    ]
    root, vdir = tmp_path / "scene", tmp_path / "videos"
    root.mkdir()
    vdir.mkdir()
    save_cameras(CameraRig(tuple(cams)), root / "cameras.json")
    for name, size in videos.items():
        _write_video(vdir / f"{name}.mp4", size)
    return root, vdir


def test_detect_maps_video_pixels_and_the_viewer_places_frames(tmp_path):
    root, vdir = _scene(tmp_path, {"enc": (88, 64), "half": (48, 32), "cut": (80, 64)})
    assert vid.probe_video(vdir / "enc.mp4").width == 88
    logs: list[str] = []
    vid.detect_scene(
        root, [vdir], progress=False, log=logs.append, detector=PointDetector(),
        video_crops={"cut": (10, 0, 6, 0)},
    )  # fmt: skip
    warned = [m for m in logs if m.startswith("warning:")]
    assert len(warned) == 2
    assert any("camera enc" in m and "cropped 8 px at the right" in m for m in warned)
    assert any("camera cut" in m and "the crop stated" in m for m in warned)
    scene = load_scene(root)
    det = scene.detections
    raw = PointDetector()(np.zeros((1, 1, 3)))  # what the detector saw, video pixels
    nose = raw.keypoints[0, 0, :2]  # COCO-17 joint 0 is BlazePose's landmark 0
    expect = {"enc": nose, "half": 2 * nose, "cut": nose + [10, 0]}
    for name, xy in expect.items():
        rows = det.view == scene.rig.index_of(name)
        np.testing.assert_allclose(det.keypoints[rows, 0, :2], np.broadcast_to(xy, (3, 2)))
    meta = json.loads((root / "scene.json").read_text())
    assert meta["video_crop"] == {"enc": [0, 0, 8, 0], "cut": [10, 0, 6, 0]}
    assert set(meta["detect"]["video_mapping"]) == {"enc", "half", "cut"}

    # the viewer shows every frame on its calibrated image: the red stripe (the
    # video's left edge) where the mapping puts it, the unseen area grey
    store = FrameStore(scene, width=96).start()
    assert store.wait(60)
    for name, (x0, x1) in {"enc": (0, 88), "cut": (10, 90), "half": (0, 48)}.items():
        img = store.frame(name, 1).astype(int)  # RGB
        assert img.shape == ((32, 48, 3) if name == "half" else (64, 96, 3)), name
        red = (img[:, :, 0] > 150) & (img[:, :, 2] < 100)
        cols = np.flatnonzero(red.mean(0) > 0.8)
        assert cols.min() == x0, name
        if name != "half":
            assert np.abs(img[:, x1 + 2 :] - FILL).max() < 12, name
            assert np.abs(img[:, : max(0, x0 - 2)] - FILL).max(initial=0) < 12, name


def test_detect_refuses_an_unknown_size_and_names_the_flag(tmp_path, capsys):
    root, vdir = _scene(tmp_path, {"cam9": (60, 64)})
    with pytest.raises(ValueError, match=r"cam9.*60x64.*96x64.*--video-crop cam9="):
        vid.detect_scene(root, [vdir], progress=False, log=print, detector=PointDetector())
    assert main(["detect", str(root), "--videos", str(vdir), "--video-crop", "cam9"]) == 2
    assert "CAM=LEFT,TOP,RIGHT,BOTTOM" in capsys.readouterr().err
    with pytest.raises(ValueError, match="not in the calibration"):
        vid.detect_scene(
            root, [vdir], progress=False, detector=PointDetector(), video_crops={"x": (0,) * 4}
        )
