"""Tests of pipeline.calibrate: boards, footage, intrinsics, extrinsics on synthetic footage
(a ChArUco board drawn by OpenCV, warped into known cameras), and the real four-webcam
session when it is present."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from pipeline.calibrate.board import Board, parse_board
from pipeline.calibrate.calibrate import calibrate_cameras, write_calibration
from pipeline.calibrate.footage import read_sync
from pipeline.calibrate.intrinsics import select_views
from pipeline.core.files import SceneFormatError
from pipeline.data.calibration_views import CALIBRATION_VIEWS, load_calibration_views
from pipeline.data.cameras import load_cameras
from pipeline.importers import read_calibration
from pipeline.importers.calibration import read_caliscope_calibration
from tests.conftest import SHARED_DATA
from tests.pipeline.calibrate_synth import (
    BOARD,
    board_poses,
    default_rig,
    moving_board,
    write_session,
)

CALISCOPE = SHARED_DATA / "caliscope_charuco"


def relative(a, b) -> tuple[np.ndarray, np.ndarray]:
    """Camera b's pose in camera a's frame: (R (3, 3), t (3,) mm)."""
    R = b.R @ a.R.T
    return R, b.t - R @ a.t


def angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    rig = default_rig()
    root = tmp_path_factory.mktemp("calib")
    return rig, write_session(root, rig, board_poses(40, seed=1))


# --------------------------------------------------------------------------- boards


def test_board_specs():
    b = parse_board("charuco:4x5:0.054:0.0405:DICT_4X4_1000:inverted")
    assert b == Board("charuco", 4, 5, 54.0, 40.5, "DICT_4X4_1000", True)
    assert b.object_points.shape == (12, 3)
    np.testing.assert_allclose(b.object_points[:2], [[54, 54, 0], [108, 54, 0]])
    c = parse_board("checkerboard:9x6:0.025")
    assert (c.kind, c.num_corners, c.square_mm) == ("checkerboard", 40, 25.0)


@pytest.mark.parametrize(
    "spec, field",
    [
        ("charuco:4x5:0.054:0.0405:DICT_NOPE", "dict"),
        ("charuco:4by5:0.054:0.0405:DICT_4X4_50", "size"),
        ("charuco:4x5:0.054:0.06:DICT_4X4_50", "marker"),
        ("checkerboard:9x6:-1", "square"),
        ("circles:4x5", "board"),
        ("charuco:4x5:0.054:0.0405:DICT_4X4_50:upside", "inverted"),
    ],
)
def test_bad_board_specs_name_the_field(spec, field):
    with pytest.raises(SceneFormatError) as exc:
        parse_board(spec)
    assert exc.value.field == field and "\n" not in str(exc.value)


def test_caliscope_board_file(tmp_path):
    path = tmp_path / "charuco.toml"
    path.write_text(
        'columns = 4\nrows = 5\ndictionary = "DICT_4X4_1000"\naruco_scale = 0.75\n'
        "square_size_override_cm = 5.4\ninverted = true\n"
    )
    assert parse_board(path) == Board("charuco", 4, 5, 54.0, 40.5, "DICT_4X4_1000", True)
    path.write_text("columns = 4\n")
    with pytest.raises(SceneFormatError, match="rows"):
        parse_board(path)


def test_checkerboard_detection_is_sub_pixel():
    board = Board("checkerboard", 6, 5, 30.0)
    image = np.full((300, 360), 255, np.uint8)
    for i in range(6):
        for j in range(5):
            if (i + j) % 2 == 0:
                image[30 + 40 * j : 70 + 40 * j, 60 + 40 * i : 100 + 40 * i] = 0
    image = cv2.GaussianBlur(image, (5, 5), 1.0)
    from pipeline.calibrate.board import board_detector

    ids, px = board_detector(board)(image)
    assert len(ids) == board.num_corners == 20
    # inner corners at x = 100 + 40 i, y = 70 + 40 j (pixel centres at integers: -0.5)
    expected = {(100 + 40 * i - 0.5, 70 + 40 * j - 0.5) for i in range(5) for j in range(4)}
    for p in px:
        assert min(np.hypot(p[0] - e[0], p[1] - e[1]) for e in expected) < 0.1


# --------------------------------------------------------------------------- footage


def test_sync_table_orders_each_cameras_frames(tmp_path):
    path = tmp_path / "timestamps.csv"
    path.write_text(
        "sync_index,cam_id,frame_index,frame_time\n"
        "7,0,26,1.0\n7,1,30,1.0\n8,0,27,1.1\n9,1,31,1.2\n9,0,28,1.2\n"
    )
    table = read_sync(path, 2)
    np.testing.assert_array_equal(table.frames, [[0, 0], [1, -1], [2, 1]])
    np.testing.assert_array_equal(table.times, [[1.0, 1.0], [1.1, np.nan], [1.2, 1.2]])
    with pytest.raises(SceneFormatError, match="cam_id"):
        read_sync(path, 1)


def test_views_chosen_for_coverage():
    corner = np.array([[10.0, 10.0], [20.0, 20.0]])
    pixels = [corner] * 5 + [corner + 500, corner + [500, 0]]
    chosen = select_views(pixels, (640, 480), max_views=3)
    assert set(chosen[:3]) >= {5, 6} and len(chosen) == 3


# --------------------------------------------------------------------------- calibration


@pytest.mark.slow
def test_synthetic_rig_recovered(session, tmp_path):
    rig, folders = session
    cal = calibrate_cameras(folders, BOARD)
    assert cal.rig.names == rig.names
    for cam, true in zip(cal.rig, rig, strict=True):
        assert (cam.width, cam.height) == (true.width, true.height)  # the portrait camera
        np.testing.assert_allclose(cam.K[[0, 1], [0, 1]], true.K[[0, 1], [0, 1]], rtol=0.025)
    for r in cal.reports:
        assert r.problem is None and r.board_frames >= 10 and r.ba_rms < 0.5, r
    for i in range(3):
        for j in range(i + 1, 3):
            R, t = relative(cal.rig[i], cal.rig[j])
            R0, t0 = relative(rig[i], rig[j])
            assert angle_deg(R @ R0.T) < 1.0
            assert np.linalg.norm(t - t0) < 0.05 * np.linalg.norm(t0)
    paths = write_calibration(cal, tmp_path / "out")
    assert [p.name for p in paths] == [
        "cameras.json", "Calib.toml", "calibration_report.html", "calibration.npz",
    ]  # fmt: skip
    back = read_calibration("pose2sim", [tmp_path / "out" / "Calib.toml"])
    np.testing.assert_allclose(back[1].t, load_cameras(paths[0])[1].t, atol=1e-6)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(
        p.name for p in paths
    )  # atomic writes: no temporary left


def test_calibration_views_saved_for_the_viewer(session, tmp_path):
    """calibration.npz holds what the viewer shows: every view's corners as detected and
    reprojected (their differences the bundle adjustment's residuals, their RMS the
    report's), the board's pose per frame, a thumbnail per view, the cameras' figures."""
    rig, folders = session
    cal = calibrate_cameras(folders[:2], BOARD, intrinsics=rig.subset([0, 1]))
    write_calibration(cal, tmp_path)
    saved = load_calibration_views(tmp_path / CALIBRATION_VIEWS)
    assert [c.name for c in saved.cameras] == ["left", "front"]
    assert saved.world == "camera:left" and not saved.z_up
    assert saved.board == {"kind": "charuco", "columns": 7, "rows": 5, "square_mm": 60.0}
    assert saved.num_views == len(cal.views)
    for k, v in enumerate(cal.views):
        ids, det, rep = saved.corners(k)
        assert (saved.view_camera[k], saved.view_frame[k]) == (v.camera, v.frame)
        np.testing.assert_array_equal(ids, v.ids)
        np.testing.assert_allclose(det, v.pixels)
        np.testing.assert_allclose(rep - det, cal.residuals[k], atol=1e-9)
        image = cv2.imdecode(np.frombuffer(saved.thumbnail(k), np.uint8), cv2.IMREAD_GRAYSCALE)
        assert image.shape == (480, 640)  # the cameras' full size: under the thumbnail side
    rms = saved.view_rms()
    for c, r in enumerate(cal.reports):
        mine = saved.view_camera == c
        counts = np.diff(saved.view_start)[mine]
        total = np.sqrt(np.sum(rms[mine] ** 2 * counts) / counts.sum())
        assert total == pytest.approx(r.ba_rms) and saved.cameras[c].ba_rms == r.ba_rms
        assert saved.cameras[c].calibrated and saved.cameras[c].footage == str(folders[c])
    assert sorted(saved.pose_frame) == sorted(cal.T_world_board)
    np.testing.assert_allclose(saved.board_pose(3), cal.T_world_board[3])
    # a foreign or damaged file is named
    np.savez(tmp_path / "other.npz", meta=np.array("{}"))
    with pytest.raises(SceneFormatError, match="other.npz"):
        load_calibration_views(tmp_path / "other.npz")
    (tmp_path / "cut.npz").write_bytes((tmp_path / CALIBRATION_VIEWS).read_bytes()[:500])
    with pytest.raises(SceneFormatError, match="cut.npz"):
        load_calibration_views(tmp_path / "cut.npz")


@pytest.mark.slow
def test_inverted_board_and_floor_frame(tmp_path):
    rig = default_rig().subset([0, 1])
    poses = board_poses(12, seed=3)
    folders = write_session(tmp_path, rig, poses, inverted=True)
    board = Board("charuco", 7, 5, 60.0, 45.0, "DICT_4X4_50", inverted=True)
    cal = calibrate_cameras(folders, board, intrinsics=rig, floor_frame=0)
    # the board of frame 0 lies on the floor: its corners at z = 0, the cameras above
    T = cal.T_world_board[0]
    corners = board.object_points @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(corners[:, 2], 0, atol=1e-6)
    assert (cal.rig.centers[:, 2] > 500).all()
    # with the true intrinsics the relative pose is tight
    R, t = relative(cal.rig[0], cal.rig[1])
    R0, t0 = relative(rig[0], rig[1])
    assert angle_deg(R @ R0.T) < 0.3 and np.linalg.norm(t - t0) < 10


@pytest.mark.slow
def test_moving_board_and_a_late_camera(tmp_path):
    """The board moves ~40 mm a frame; "front" takes each frame half a frame later than the
    others: the bundle adjustment finds the offset and sees the board where it was."""
    rig = default_rig()
    late = {"front": 0.5}
    poses = {c.name: [moving_board(k + late.get(c.name, 0.0)) for k in range(30)] for c in rig}
    folders = write_session(tmp_path, rig, poses)
    cal = calibrate_cameras(folders, BOARD, intrinsics=rig)
    offsets = {r.name: r.sync_offset_frames for r in cal.reports}
    assert offsets["left"] == 0 and abs(offsets["right"]) < 0.05, offsets
    assert abs(offsets["front"] - 0.5) < 0.05, offsets
    assert all(r.ba_rms < 0.4 for r in cal.reports), cal.reports
    still = calibrate_cameras(folders, BOARD, intrinsics=rig, sync_offsets=False)
    assert still.reports[1].ba_rms > 3 * cal.reports[1].ba_rms  # the late camera, unmodelled
    for fit in (cal, still):
        assert np.isnan(fit.reports[1].sync_offset_s)  # no sync table: no seconds
    for i, j in ((0, 1), (1, 2)):
        R, t = relative(cal.rig[i], cal.rig[j])
        R0, t0 = relative(rig[i], rig[j])
        assert angle_deg(R @ R0.T) < 0.2 and np.linalg.norm(t - t0) < 5


@pytest.mark.slow
def test_camera_with_too_few_views_is_named(tmp_path):
    rig = default_rig()
    poses = board_poses(24, seed=4)
    hidden = {"right": set(range(2, 24))}
    folders = write_session(tmp_path, rig, poses, blank=hidden)
    cal = calibrate_cameras(folders, BOARD)
    assert cal.rig.names == ["left", "front"]
    right = cal.reports[2]
    assert right.problem is not None and right.name == "right"
    assert f"in {right.board_frames} of 24 frames" in right.problem


def test_no_shared_view_and_no_board_are_errors(tmp_path):
    rig = default_rig().subset([0, 1])
    poses = board_poses(10, seed=5)
    folders = write_session(tmp_path / "a", rig, poses,
                            blank={"left": set(range(5)), "front": set(range(5, 10))})  # fmt: skip
    with pytest.raises(SceneFormatError, match="no two cameras see the board in the same frame"):
        calibrate_cameras(folders, BOARD, intrinsics=rig)
    folders = write_session(tmp_path / "b", rig, poses[:3], blank={c: {0, 1, 2} for c in rig.names})
    with pytest.raises(SceneFormatError, match="in no frame of any camera"):
        calibrate_cameras(folders, BOARD)


def test_video_that_does_not_open(tmp_path):
    bad = tmp_path / "cam.mp4"
    bad.write_bytes(b"not a video")
    with pytest.raises(SceneFormatError, match="not a video"):
        calibrate_cameras([bad, bad.with_name("other.mp4")], BOARD)


def test_caliscope_calibration_format(tmp_path):
    path = tmp_path / "camera_array.toml"
    path.write_text(
        "[cameras.0]\ncam_id = 0\nsize = [640, 480]\n"
        "matrix = [[600.0, 0.0, 320.0], [0.0, 601.0, 240.0], [0.0, 0.0, 1.0]]\n"
        "distortions = [0.1, -0.2, 0.001, 0.002, 0.05]\n"
        "rotation = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]\n"
        "translation = [0.1, -0.2, 1.5]\n"
        "[cameras.1]\ncam_id = 1\nsize = [640, 480]\nignore = true\n"
    )
    rig = read_calibration("caliscope", [path])
    assert rig.names == ["cam_0"]
    np.testing.assert_allclose(rig[0].t, [100, -200, 1500])
    np.testing.assert_allclose(rig[0].dist, [0.1, -0.2, 0.001, 0.002, 0.05])
    path.write_text(path.read_text().replace("translation = [0.1, -0.2, 1.5]\n", ""))
    with pytest.raises(SceneFormatError, match="cameras.0.translation"):
        read_caliscope_calibration(path)
    assert read_caliscope_calibration(path, require_poses=False)[0].K[1, 1] == 601


@pytest.mark.slow
@pytest.mark.skipif(not CALISCOPE.is_dir(), reason="the shared Caliscope session is absent")
def test_real_four_webcam_session():
    videos = [CALISCOPE / "extrinsic" / f"cam_{k}.mp4" for k in range(4)]
    cal = calibrate_cameras(
        videos,
        parse_board(CALISCOPE / "charuco.toml"),
        sync=CALISCOPE / "extrinsic" / "timestamps.csv",
        intrinsics=read_caliscope_calibration(CALISCOPE / "camera_array.toml"),
    )
    assert cal.rig.names == [f"cam_{k}" for k in range(4)]
    assert [r.board_frames for r in cal.reports] == [46, 33, 44, 45]
    for r in cal.reports:
        assert r.problem is None and r.ba_rms < 1.0, r
    # cam_1 stamps its frames late: they were taken 0.84 frame before the others
    offsets = [r.sync_offset_frames for r in cal.reports]
    assert offsets[0] == 0 and -0.95 < offsets[1] < -0.75, offsets
    assert all(abs(o) < 0.3 for o in offsets[2:]), offsets
