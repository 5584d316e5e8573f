"""Tests of pipeline.importers: calibration readers / writers and detection readers.

Units: millimetres in the native rig; EasyMocap and Pose2Sim files are in metres.
"""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from pipeline.core.files import SceneFormatError
from pipeline.data.cameras import CameraRig, make_camera
from pipeline.data.joint_sets import BODY25, COCO17
from pipeline.data.scene import load_scene
from pipeline.importers import (
    CALIBRATION_FORMATS,
    OPENPOSE_COCO18,
    convert_scene,
    read_calibration,
    read_easymocap_annots,
    read_easymocap_calibration,
    read_openpose_folders,
    read_pose2sim_calibration,
    read_voxelpose_calibration,
    write_easymocap_calibration,
    write_pose2sim_calibration,
    write_voxelpose_calibration,
)
from pipeline.importers.detections import frame_index
from tests.conftest import SHELF_REAL

# the real Shelf/Campus rigs, shipped byte-identical to ../shared/data/calibration
CALIBRATION_DIR = Path(__file__).resolve().parents[2] / "sample_data" / "rigs"
REAL_RIGS = {
    # file, number of cameras, (width, height)
    "shelf": ("shelf_voxelpose.json", 5, (1032, 776)),
    "campus": ("campus_voxelpose.json", 3, (360, 288)),
}


def real_rig_path(which: str) -> Path:
    return CALIBRATION_DIR / REAL_RIGS[which][0]


def assert_rigs_equal(a: CameraRig, b: CameraRig, atol: float = 1e-6) -> None:
    assert a.names == b.names
    for ca, cb in zip(a, b, strict=True):
        assert (ca.width, ca.height) == (cb.width, cb.height), ca.name
        np.testing.assert_allclose(cb.K, ca.K, atol=atol, rtol=0, err_msg=f"{ca.name} K")
        np.testing.assert_allclose(cb.dist, ca.dist, atol=atol, rtol=0, err_msg=f"{ca.name} dist")
        np.testing.assert_allclose(cb.R, ca.R, atol=atol, rtol=0, err_msg=f"{ca.name} R")
        np.testing.assert_allclose(cb.t, ca.t, atol=atol, rtol=0, err_msg=f"{ca.name} t")


def with_dist(rig: CameraRig, dist) -> CameraRig:
    return CameraRig(tuple(dataclasses.replace(c, dist=np.asarray(dist, float)) for c in rig))


def write_calibration(fmt: str, rig: CameraRig, directory: Path) -> list[Path]:
    """Write ``rig`` in ``fmt`` under ``directory``; returns the paths to read it back."""
    if fmt == "easymocap":
        return list(write_easymocap_calibration(rig, directory))
    path = directory / {"pose2sim": "Calib.toml", "voxelpose": "cameras_vp.json"}[fmt]
    CALIBRATION_FORMATS[fmt].write(rig, path)
    return [path]


# --------------------------------------------------------------------------- real rigs


@pytest.mark.parametrize("which", sorted(REAL_RIGS))
def test_real_voxelpose_rigs(which):
    path = real_rig_path(which)
    _, num_cameras, size = REAL_RIGS[which]
    rig = read_voxelpose_calibration(path)
    raw = json.loads(path.read_text())

    assert len(rig) == num_cameras
    assert rig.names == list(raw)
    for cam in rig:
        assert (cam.width, cam.height) == size
        # T in the json is the camera centre (x_cam = R (X - T)).
        np.testing.assert_allclose(cam.center, np.ravel(raw[cam.name]["T"]), atol=1e-6)
        np.testing.assert_allclose(cam.R, raw[cam.name]["R"], atol=5e-6)  # stored rounded
        np.testing.assert_allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-12)
        assert cam.K[0, 0] == raw[cam.name]["fx"] and cam.K[1, 2] == raw[cam.name]["cy"]

        # 1 m straight ahead lands on the principal point; 1 m ahead and 20 cm off-axis
        # lands inside the image.
        ahead = cam.center + 1000.0 * cam.R[2]
        np.testing.assert_allclose(cam.project(ahead), cam.K[:2, 2], atol=1e-6)
        for offset in (cam.R[0], -cam.R[0], cam.R[1], -cam.R[1]):
            u, v = cam.project(ahead + 200.0 * offset)
            assert 0 <= u < cam.width and 0 <= v < cam.height
            assert np.hypot(u - cam.K[0, 2], v - cam.K[1, 2]) < 0.5 * max(size)


@pytest.mark.parametrize("which", sorted(REAL_RIGS))
@pytest.mark.parametrize("dist", [None, [0.12, -0.3, 0.002, -0.001, 0.05]])
def test_project_agrees_with_cv2(which, dist):
    rig = read_voxelpose_calibration(real_rig_path(which))
    if dist is not None:
        rig = with_dist(rig, dist)
    rng = np.random.default_rng(0)
    for cam in rig:
        # Points 1-6 m in front of the camera, within +-30 degrees of the axis.
        d_cam = np.column_stack([rng.uniform(-0.5, 0.5, (200, 2)), np.ones(200)])
        points = cam.center + (rng.uniform(1000, 6000, (200, 1)) * d_cam) @ cam.R
        rvec, _ = cv2.Rodrigues(cam.R)
        expected, _ = cv2.projectPoints(points, rvec, cam.t, cam.K, cam.dist)
        np.testing.assert_allclose(cam.project(points), expected[:, 0], atol=1e-6, rtol=0)


def _voxelpose_project(X, R, T, f, c, k, p):
    """VoxelPose's ``project_point_radial`` (lib/utils/cameras.py), restated: (N, 3) -> (N, 2)."""
    xcam = R @ (X.T - T)
    y = xcam[:2] / xcam[2]
    r2 = (y**2).sum(0)
    radial = 1 + k[0] * r2 + k[1] * r2**2 + k[2] * r2**3
    tan = p[0] * y[1] + p[1] * y[0]
    y = y * (radial + 2 * tan) + np.outer([p[1], p[0]], r2)
    return (f * y + c).T


def test_voxelpose_distortion_convention(tmp_path):
    """k = (k1, k2, k3) and p = (p1, p2) mean what OpenCV means by them."""
    R = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()
    T = np.array([[100.0], [-2000.0], [1500.0]])
    f, c, k, p = [[1000.0], [990.0]], [[500.0], [380.0]], [0.1, -0.05, 0.02], [0.003, -0.002]
    cam = {"R": R.tolist(), "T": T.tolist(), "k": np.reshape(k, (3, 1)).tolist()}
    cam |= {"p": np.reshape(p, (2, 1)).tolist(), "fx": 1000.0, "fy": 990.0, "cx": 500.0}
    cam |= {"cy": 380.0, "width": 1000, "height": 760}
    path = tmp_path / "vp.json"
    path.write_text(json.dumps({"cam": cam}))
    rig = read_voxelpose_calibration(path)
    np.testing.assert_allclose(rig[0].dist, [0.1, -0.05, 0.003, -0.002, 0.02])
    rng = np.random.default_rng(1)
    X = rig[0].center + (rng.uniform(-0.4, 0.4, (50, 3)) + [0, 0, 1]) * 3000 @ R
    expected = _voxelpose_project(X, R, T, np.array(f), np.array(c), k, p)
    np.testing.assert_allclose(rig[0].project(X), expected, atol=1e-6)


# --------------------------------------------------------------------------- round trips


DIST5 = [0.1, -0.05, 0.001, -0.002, 0.01]
DIST4 = [0.1, -0.05, 0.001, -0.002, 0.0]  # Pose2Sim stores no k3


@pytest.mark.parametrize("which", sorted(REAL_RIGS))
@pytest.mark.parametrize(
    ("fmt", "dist"),
    [("easymocap", DIST5), ("voxelpose", DIST5), ("pose2sim", DIST4), ("easymocap", None)],
)
def test_round_trip_real_rigs(tmp_path, which, fmt, dist):
    rig = read_voxelpose_calibration(real_rig_path(which))
    if dist is not None:
        rig = with_dist(rig, dist)
    back = read_calibration(fmt, write_calibration(fmt, rig, tmp_path))
    assert_rigs_equal(rig, back)


def test_pose2sim_drops_k3_with_a_warning(tmp_path):
    rig = with_dist(read_voxelpose_calibration(real_rig_path("campus")), DIST5)
    with pytest.warns(UserWarning, match="k3"):
        write_pose2sim_calibration(rig, tmp_path / "Calib.toml")
    back = read_pose2sim_calibration(tmp_path / "Calib.toml")
    assert_rigs_equal(with_dist(rig, DIST4), back)  # everything but k3 survives


def test_round_trip_through_convert_scene(tmp_path):
    rig = read_voxelpose_calibration(real_rig_path("shelf"))
    for fmt in ("easymocap", "pose2sim", "voxelpose"):
        paths = write_calibration(fmt, rig, tmp_path / f"in_{fmt}")
        out = convert_scene(calib_format=fmt, calib_paths=paths, out_dir=tmp_path / fmt)
        scene = load_scene(out)
        assert_rigs_equal(rig, scene.rig)
        assert len(scene.detections) == 0 and scene.joint_set.name == "coco17"


def test_easymocap_directory_and_swapped_files(tmp_path):
    rig = read_voxelpose_calibration(real_rig_path("campus"))
    intri, extri = write_easymocap_calibration(rig, tmp_path)
    assert_rigs_equal(rig, read_calibration("easymocap", [tmp_path]))
    assert_rigs_equal(rig, read_calibration("easymocap", [extri, intri]))


# --------------------------------------------------------------------------- hypothesis


def _rig_strategy():
    unit = st.floats(-1.0, 1.0, allow_nan=False)
    camera = st.fixed_dictionaries(
        {
            "quat": st.tuples(unit, unit, unit, unit).filter(lambda q: np.linalg.norm(q) > 0.1),
            "t": st.tuples(*[st.floats(-2e4, 2e4, allow_nan=False)] * 3),
            "f": st.floats(50.0, 1e4),
            "aspect": st.floats(0.5, 2.0),
            "skew": st.sampled_from([0.0, 0.0, 1.5]),
            "c": st.tuples(st.floats(0, 4000), st.floats(0, 4000)),
            "size": st.tuples(st.integers(1, 8000), st.integers(1, 8000)),
            "dist": st.tuples(*[st.floats(-1.0, 1.0, allow_nan=False)] * 5),
        }
    )
    names = st.lists(
        st.from_regex(r"[A-Za-z0-9_-]{1,10}", fullmatch=True), min_size=1, max_size=4, unique=True
    )
    return names.flatmap(
        lambda ns: st.tuples(st.just(ns), st.lists(camera, min_size=len(ns), max_size=len(ns)))
    )


def _make_rig(names, params) -> CameraRig:
    cams = []
    for name, p in zip(names, params, strict=True):
        f, (cx, cy), (w, h) = p["f"], p["c"], p["size"]
        K = [[f, p["skew"], cx], [0, f * p["aspect"], cy], [0, 0, 1]]
        R = Rotation.from_quat(p["quat"]).as_matrix()
        cams.append(make_camera(name=name, width=w, height=h, K=K, dist=p["dist"], R=R, t=p["t"]))
    return CameraRig(tuple(cams))


@pytest.mark.slow
@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=_rig_strategy())
def test_random_rigs_survive_round_trips(tmp_path_factory, data):
    names, params = data
    rig = _make_rig(names, params)
    directory = tmp_path_factory.mktemp("rt")
    paths = write_calibration("easymocap", rig, directory)
    assert_rigs_equal(rig, read_calibration("easymocap", paths))

    # Pose2Sim has no k3.
    rig4 = CameraRig(tuple(dataclasses.replace(c, dist=np.append(c.dist[:4], 0.0)) for c in rig))
    assert_rigs_equal(
        rig4, read_calibration("pose2sim", write_calibration("pose2sim", rig4, directory))
    )
    no_skew = CameraRig(tuple(c for c in rig if c.K[0, 1] == 0))
    if len(no_skew):
        back = read_calibration("voxelpose", write_calibration("voxelpose", no_skew, directory))
        assert_rigs_equal(no_skew, back)


def test_easymocap_names_that_look_like_yaml_values(tmp_path):
    names = ["1e5", "true", "null", "007", "-1", "Yes", "inf"]
    rig = CameraRig(
        tuple(
            make_camera(
                name=n,
                width=640,
                height=480,
                K=[[500, 0, 320], [0, 500, 240], [0, 0, 1]],
                dist=np.zeros(5),
                R=np.eye(3),
                t=[0.0, 0.0, 1000.0 + i],
            )
            for i, n in enumerate(names)
        )
    )
    for fmt in ("easymocap", "pose2sim", "voxelpose"):
        back = read_calibration(fmt, write_calibration(fmt, rig, tmp_path / fmt))
        assert_rigs_equal(rig, back)


# --------------------------------------------------------------------------- hand-written files

# As EasyMocap's FileStorage class writes them: "%YAML:1.0", CRLF, 6 decimals, no H_/W_.
EASYMOCAP_INTRI = """%YAML:1.0
---
names:
  - "01"
  - "cam3"
K_01: !!opencv-matrix
  rows: 3
  cols: 3
  dt: d
  data: [1100.500000, 0.000000, 960.250000, 0.000000, 1101.750000, 540.125000, 0.000000, \
0.000000, 1.000000]
dist_01: !!opencv-matrix
  rows: 1
  cols: 5
  dt: d
  data: [-0.120000, 0.050000, 0.001000, -0.002000, 0.000000]
K_cam3: !!opencv-matrix
  rows: 3
  cols: 3
  dt: d
  data: [800.000000, 0.000000, 640.000000, 0.000000, 800.000000, 360.000000, 0.000000, \
0.000000, 1.000000]
dist_cam3: !!opencv-matrix
  rows: 1
  cols: 5
  dt: d
  data: [0.000000, 0.000000, 0.000000, 0.000000, 0.000000]
""".replace("\n", "\r\n")

EASYMOCAP_EXTRI = """%YAML:1.0
---
names:
  - "01"
  - "cam3"
R_01: !!opencv-matrix
  rows: 3
  cols: 1
  dt: d
  data: [0.100000, -0.200000, 0.300000]
Rot_01: !!opencv-matrix
  rows: 3
  cols: 3
  dt: d
  data: [0.935755, -0.302933, -0.180540, 0.283165, 0.950581, -0.127335, 0.210192, \
0.068031, 0.975290]
T_01: !!opencv-matrix
  rows: 3
  cols: 1
  dt: d
  data: [0.500000, -1.250000, 4.000000]
R_cam3: !!opencv-matrix
  rows: 3
  cols: 1
  dt: d
  data: [0.000000, 3.141593, 0.000000]
Rot_cam3: !!opencv-matrix
  rows: 3
  cols: 3
  dt: d
  data: [-1.000000, 0.000000, 0.000000, 0.000000, 1.000000, 0.000000, -0.000000, \
0.000000, -1.000000]
T_cam3: !!opencv-matrix
  rows: 3
  cols: 1
  dt: d
  data: [0.000000, 0.000000, 6.000000]
""".replace("\n", "\r\n")


def write_easymocap_text(
    directory: Path, intri: str = EASYMOCAP_INTRI, extri: str = EASYMOCAP_EXTRI
):
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "intri.yml").write_bytes(intri.encode())
    (directory / "extri.yml").write_bytes(extri.encode())
    return directory / "intri.yml", directory / "extri.yml"


def test_easymocap_hand_written(tmp_path):
    intri, extri = write_easymocap_text(tmp_path)
    with pytest.raises(SceneFormatError, match=r"intri\.yml.*H_01.*image_size"):
        read_easymocap_calibration(intri, extri)
    rig = read_easymocap_calibration(intri, extri, image_size=(1920, 1080))
    assert rig.names == ["01", "cam3"]
    c = rig[0]
    assert (c.width, c.height) == (1920, 1080)
    np.testing.assert_array_equal(c.K, [[1100.5, 0, 960.25], [0, 1101.75, 540.125], [0, 0, 1]])
    np.testing.assert_array_equal(c.dist, [-0.12, 0.05, 0.001, -0.002, 0.0])
    np.testing.assert_allclose(c.R, Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(c.t, [500.0, -1250.0, 4000.0])  # metres -> mm
    np.testing.assert_allclose(rig[1].center, [0.0, 0.0, 6000.0], atol=1e-2)


def test_easymocap_image_size_from_file_and_rot_only(tmp_path):
    intri = EASYMOCAP_INTRI + "H_01: 1080\r\nW_01: 1920\r\nH_cam3: 720\r\nW_cam3: 1280\r\n"
    # Without the Rodrigues R_<cam>, Rot_<cam> is used.
    extri = EASYMOCAP_EXTRI.replace("R_01:", "Unused_01:").replace("R_cam3:", "Unused_cam3:")
    rig = read_easymocap_calibration(*write_easymocap_text(tmp_path, intri, extri))
    assert [(c.width, c.height) for c in rig] == [(1920, 1080), (1280, 720)]
    np.testing.assert_allclose(
        rig[0].R, Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix(), atol=2e-6
    )
    np.testing.assert_allclose(rig[0].R @ rig[0].R.T, np.eye(3), atol=1e-12)


# Pose2Sim's own writer (calibration.py toml_write): tables named after cameras, float sizes,
# 4 distortions, trailing [metadata].
POSE2SIM_TOML = """[cam_01]
name = "cam_01"
size = [ 1088.0, 1920.0]
matrix = [ [ 1681.244873046875, 0.0, 532.97369384375], [ 0.0, 1681.075439453125, \
948.137390140625], [ 0.0, 0.0, 1.0]]
distortions = [ -0.000721609375, 0.002187234375, 9.5e-06, 1.078125e-05]
rotation = [ 1.6882754799999993, 1.0483220499999997, -0.41955852000000016]
translation = [ 0.32110488999999953, 0.9563320600000009, 2.8907130499999996]
fisheye = false

[cam_02]
name = "cam_02"
size = [ 1088.0, 1920.0]
matrix = [ [ 1673.729614265625, 0.0, 534.494567875], [ 0.0, 1673.79724121875, \
963.225891109375], [ 0.0, 0.0, 1.0]]
distortions = [ -0.000747609375, 0.00213728125, 1.51875e-05, 4.546875e-06]
rotation = [ 1.34975875, 1.5963809099999993, -1.1983285799999999]
translation = [ -0.1115282900000002, 0.7766184800000001, 3.0675519599999994]
fisheye = false

[metadata]
adjusted = false
error = 0.0
"""

# aniposelib's writer: tables cam_<i>, the camera's name inside, int sizes, 5 distortions.
ANIPOSE_TOML = """[cam_0]
name = "cam088"
size = [ 1440, 1080,]
matrix = [ [ 1850.506308260702, 0.0, 719.5,], [ 0.0, 1850.506308260702, 539.5,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.18925717533695158, 0.0, 0.0, 0.0, 0.0,]
rotation = [ -0.0016129363863306178, -0.002441180452093902, -0.007465964724818265,]
translation = [ 1.623648987402533, -0.601652230518438, 20.748877329963953,]

[metadata]
adjusted = false
error = 0.16285923171540084
"""


def test_pose2sim_hand_written(tmp_path):
    path = tmp_path / "Calib.toml"
    path.write_text(POSE2SIM_TOML)
    rig = read_pose2sim_calibration(path)
    assert rig.names == ["cam_01", "cam_02"]
    c = rig[0]
    assert (c.width, c.height) == (1088, 1920)  # size is [width, height]
    np.testing.assert_array_equal(c.K[0], [1681.244873046875, 0.0, 532.97369384375])
    np.testing.assert_array_equal(
        c.dist, [-0.000721609375, 0.002187234375, 9.5e-06, 1.078125e-05, 0]
    )
    rvec = np.array([1.6882754799999993, 1.0483220499999997, -0.41955852000000016])
    tvec = np.array([0.32110488999999953, 0.9563320600000009, 2.8907130499999996])
    np.testing.assert_allclose(c.R, Rotation.from_rotvec(rvec).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(c.t, 1000 * tvec)
    # Agrees with OpenCV's reading of the same numbers (metres in, pixels out).
    X = np.array([[0.1, 0.2, 0.3], [-0.5, 0.4, 1.0]])
    expected, _ = cv2.projectPoints(X, rvec, tvec, c.K, c.dist[:4])
    np.testing.assert_allclose(c.project(1000 * X), expected[:, 0], atol=1e-6)


def test_aniposelib_hand_written(tmp_path):
    path = tmp_path / "calibration.toml"
    path.write_text(ANIPOSE_TOML)
    rig = read_calibration("pose2sim", [path])
    assert rig.names == ["cam088"]  # the name inside the table, not the table's
    assert (rig[0].width, rig[0].height) == (1440, 1080)
    np.testing.assert_allclose(rig[0].dist, [-0.18925717533695158, 0, 0, 0, 0])
    np.testing.assert_allclose(rig[0].t, [1623.648987402533, -601.652230518438, 20748.877329963953])


def test_pose2sim_rejects_fisheye(tmp_path):
    path = tmp_path / "Calib.toml"
    path.write_text(POSE2SIM_TOML.replace("fisheye = false", "fisheye = true", 1))
    with pytest.raises(SceneFormatError, match=r"Calib\.toml: field 'cam_01\.fisheye'.*fisheye"):
        read_pose2sim_calibration(path)


def test_voxelpose_unknown_rig_needs_image_size(tmp_path):
    path = tmp_path / "vp.json"
    raw = json.loads(real_rig_path("shelf").read_text())
    raw["0"]["fx"] += 10.0  # no longer the Shelf rig
    path.write_text(json.dumps(raw))
    with pytest.raises(SceneFormatError, match=r"vp\.json: field '0\.width'.*image_size"):
        read_voxelpose_calibration(path)
    rig = read_voxelpose_calibration(path, image_size=(800, 600))
    assert all((c.width, c.height) == (800, 600) for c in rig)


# --------------------------------------------------------------------------- detections


def make_person(num_joints: int, seed: int, missing: int | None = None) -> np.ndarray:
    """(num_joints, 3) keypoints whose x encodes (seed, joint): x = 1000 * seed + joint."""
    j = np.arange(num_joints, dtype=float)
    kp = np.column_stack([1000.0 * seed + j, 2.0 * j + 0.5, np.linspace(0.3, 0.9, num_joints)])
    if missing is not None:
        kp[missing] = 0.0  # OpenPose writes a missed joint as 0, 0, 0
    return kp


def write_openpose(root: Path, camera: str, frame: int, people: list[np.ndarray]) -> Path:
    path = root / camera / f"{camera}_{frame:012d}_keypoints.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    empty = dict.fromkeys(["face_keypoints_2d", "hand_left_keypoints_2d"], [])
    people_json = [{"pose_keypoints_2d": np.ravel(p).tolist(), **empty} for p in people]
    body = {"version": 1.3, "people": people_json}
    path.write_text(json.dumps(body))
    return path


def write_annots(root: Path, camera: str, frame: int, people: list[np.ndarray], bare=False):
    path = root / camera / f"{frame:06d}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    annots = [
        {"personID": i, "bbox": [0, 0, 10, 10, 0.9], "keypoints": np.asarray(p).tolist()}
        for i, p in enumerate(people)
    ]
    header = {"filename": f"images/{camera}/{frame:06d}.jpg", "height": 1080, "width": 1920}
    body = annots if bare else {**header, "annots": annots, "isKeyframe": False}
    path.write_text(json.dumps(body))
    return path


def test_openpose_body25(tmp_path):
    root = tmp_path / "openpose"
    write_openpose(root, "0", 0, [make_person(25, 1, missing=4), make_person(25, 2)])
    write_openpose(root, "0", 1, [])  # nobody detected: a normal, empty frame
    write_openpose(root, "0", 2, [make_person(25, 3)])
    write_openpose(root, "1", 0, [make_person(25, 4)])
    write_openpose(root, "1", 3, [make_person(25, 5)])
    with pytest.warns(UserWarning, match=r"camera\(s\) \['2'\]"):
        imp = read_openpose_folders(root, ["0", "1", "2"], "coco17", layout="body25")

    det = imp.detections
    assert imp.source_layout == "body25" and imp.joint_set is COCO17
    assert imp.num_frames == 4 and imp.missing_views == ("2",)
    assert imp.view_names == ("0", "1", "2")
    np.testing.assert_array_equal(det.frame, [0, 0, 0, 2, 3])
    np.testing.assert_array_equal(det.view, [0, 0, 1, 0, 1])
    seeds = [1, 2, 4, 3, 5]
    assert det.keypoints.shape == (5, 17, 3)
    for row, seed in enumerate(seeds):
        for name in ("left_wrist", "right_wrist", "nose", "left_ankle", "right_hip", "left_ear"):
            src = make_person(25, seed)[BODY25.index[name]]
            got = det.keypoints[row, COCO17.index[name]]
            if not (seed == 1 and name == "right_wrist"):
                np.testing.assert_allclose(got, src, err_msg=f"{name} of person {seed}")
    # BODY_25 joint 4 (right_wrist) of person 1 was missed: confidence 0, no position.
    missed = det.keypoints[0, COCO17.index["right_wrist"]]
    assert missed[2] == 0 and np.isnan(missed[:2]).all()


def test_openpose_coco18(tmp_path):
    root = tmp_path / "op"
    write_openpose(root, "a", 7, [make_person(18, 1)])
    imp = read_openpose_folders(root, ["a"], "coco17", layout="coco18")
    assert imp.source_layout == "coco18" and imp.num_frames == 8
    person = make_person(18, 1)
    kp = imp.detections.keypoints[0]
    for name in COCO17.names:  # every COCO-17 joint is in OpenPose's COCO-18, by name
        np.testing.assert_allclose(kp[COCO17.index[name]], person[OPENPOSE_COCO18.index[name]])
    # OpenPose COCO puts the neck at 1, so COCO-18 index != COCO-17 index from there on.
    assert OPENPOSE_COCO18.index["left_hip"] == 11 and COCO17.index["left_hip"] == 11
    assert OPENPOSE_COCO18.index["right_hip"] == 8 and COCO17.index["right_hip"] == 12
    np.testing.assert_allclose(kp[12, 0], 1000.0 + 8)

    # Into BODY_25: the neck is kept, mid_hip and the feet are missing.
    imp25 = read_openpose_folders(root, ["a"], "body25", layout="coco18")
    kp25 = imp25.detections.keypoints[0]
    np.testing.assert_allclose(kp25[BODY25.index["neck"]], person[1])
    assert kp25[BODY25.index["mid_hip"], 2] == 0 and kp25[BODY25.index["left_heel"], 2] == 0


def test_openpose_forced_layout_and_unknown_count(tmp_path):
    root = tmp_path / "op"
    write_openpose(root, "a", 0, [make_person(18, 1)])
    with pytest.raises(
        SceneFormatError,
        match=r"a_000000000000_keypoints\.json: field "
        r"'people\[0\]\.pose_keypoints_2d': expected 25 keypoints",
    ):
        read_openpose_folders(root, ["a"], layout="body25")
    write_openpose(root, "a", 0, [make_person(15, 1)])
    with pytest.raises(SceneFormatError, match=r"people\[0\]\.pose_keypoints_2d.*15 keypoints"):
        read_openpose_folders(root, ["a"])
    with pytest.raises(SceneFormatError, match=r"op: field 'layout'"):
        read_openpose_folders(root, ["a"], layout="mpi15")


def test_openpose_mixed_layouts_are_an_error(tmp_path):
    root = tmp_path / "op"
    write_openpose(root, "a", 0, [make_person(25, 1)])
    write_openpose(root, "a", 1, [make_person(25, 1), make_person(18, 2)])
    with pytest.raises(SceneFormatError, match=r"people\[1\]\.pose_keypoints_2d.*expected 25"):
        read_openpose_folders(root, ["a"])


def test_easymocap_annots(tmp_path):
    root = tmp_path / "annots"
    write_annots(root, "01", 0, [make_person(25, 1), make_person(25, 2)])
    write_annots(root, "01", 1, [])
    write_annots(root, "02", 1, [make_person(25, 3)], bare=True)  # old files: a bare list
    imp = read_easymocap_annots(root, ["01", "02"], "coco17", layout="body25")
    np.testing.assert_array_equal(imp.detections.frame, [0, 0, 1])
    np.testing.assert_array_equal(imp.detections.view, [0, 0, 1])
    assert imp.num_frames == 2 and imp.source_layout == "body25" and imp.missing_views == ()
    lw = imp.detections.keypoints[:, COCO17.index["left_wrist"]]
    np.testing.assert_allclose(lw[:, 0], [1007.0, 2007.0, 3007.0])  # BODY_25 left_wrist = 7


def test_no_people_anywhere_gives_zero_rows(tmp_path):
    root = tmp_path / "op"
    for f in range(3):
        write_openpose(root, "a", f, [])
    imp = read_openpose_folders(root, ["a"], "halpe26")
    assert len(imp.detections) == 0 and imp.detections.keypoints.shape == (0, 26, 3)
    assert imp.num_frames == 3 and imp.source_layout is None


def test_scores_are_kept_as_detectors_write_them(tmp_path):
    """A confidence is a detector's score: above 1 kept, zero / negative / NaN missing."""
    root = tmp_path / "op"
    p = make_person(25, 1)
    p[3, 2] = 1.008  # an OpenPose heatmap peak above 1, as in real Shelf detections
    p[4, 2] = 1.407
    p[5] = [12.0, 34.0, 0.0]  # a zero score with coordinates: missing all the same
    p[6, 2] = -0.2
    p[7, 2] = float("nan")
    write_openpose(root, "a", 0, [p])
    kp = read_openpose_folders(root, ["a"], "body25", layout="body25").detections.keypoints[0]
    assert kp[3, 2] == 1.008 and kp[4, 2] == 1.407
    np.testing.assert_array_equal(kp[3, :2], p[3, :2])
    for j in (5, 6, 7):
        assert kp[j, 2] == 0.0 and np.isnan(kp[j, :2]).all()
    np.testing.assert_array_equal(kp[8:], p[8:])


def test_only_what_is_not_a_score_is_refused(tmp_path):
    root = tmp_path / "op"
    p = make_person(25, 1)
    for bad, message in ((float("inf"), "inf"), ("0.5", "number")):
        values = np.ravel(p).tolist()
        values[3 * 3 + 2] = bad
        path = write_openpose(root, "a", 0, [make_person(25, 0)])
        body = json.loads(path.read_text())
        body["people"].append({"pose_keypoints_2d": values})
        # json.dumps writes inf as Infinity, which Python's reader takes as a number
        path.write_text(json.dumps(body))
        with pytest.raises(SceneFormatError) as info:
            read_openpose_folders(root, ["a"])
        text = str(info.value)
        assert path.name in text and "people[1].pose_keypoints_2d" in text and message in text
        assert "\n" not in text


def test_openpose_file_variants(tmp_path):
    """OpenPose 1.x as written: with and without ``person_id``, hands and faces present or
    not, an empty ``people`` list, a person with only hands (empty body)."""
    root = tmp_path / "op"
    a, b = make_person(25, 1), make_person(25, 2)
    bodies = {
        0: {"version": 1.3, "people": [
            {"person_id": [-1], "pose_keypoints_2d": np.ravel(a).tolist(),
             "face_keypoints_2d": [], "hand_left_keypoints_2d": [],
             "hand_right_keypoints_2d": [], "pose_keypoints_3d": []},
            {"pose_keypoints_2d": np.ravel(b).tolist()},
        ]},
        1: {"version": 1.2, "people": []},
        2: {"version": 1.3, "people": [
            {"person_id": [-1], "pose_keypoints_2d": [],
             "hand_left_keypoints_2d": [1.0, 2.0, 0.5] * 21},
            {"person_id": [-1], "pose_keypoints_2d": np.ravel(b).tolist(),
             "face_keypoints_2d": [3.0, 4.0, 0.7] * 70},
        ]},
    }
    for frame, body in bodies.items():
        path = root / "a" / f"a_{frame:012d}_keypoints.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(body))
    imp = read_openpose_folders(root, ["a"], "body25", layout="body25")
    assert imp.num_frames == 3
    np.testing.assert_array_equal(imp.detections.frame, [0, 0, 2])
    np.testing.assert_array_equal(imp.detections.keypoints[:, 0, 0], [1000.0, 2000.0, 2000.0])


@pytest.mark.skipif(not SHELF_REAL.is_dir(), reason="../shared/data/shelf_real is absent")
def test_real_shelf_openpose_is_read_whole():
    """The real Shelf OpenPose output (scores up to 1.008) reads with no detection lost."""
    root = SHELF_REAL / "openpose"
    names = sorted(p.name for p in root.iterdir())
    imp = read_openpose_folders(root, names, layout="body25")
    people = 0
    top = 0.0
    for name in names:
        for path in (root / name).glob("*.json"):
            for person in json.loads(path.read_text())["people"]:
                if person["pose_keypoints_2d"]:
                    people += 1
                    top = max(top, max(person["pose_keypoints_2d"][2::3]))
    assert len(imp.detections) == people > 1000
    assert top > 1.0
    assert imp.detections.keypoints[..., 2].max() == pytest.approx(top)


def test_bad_detection_files(tmp_path):
    root = tmp_path / "op"
    path = write_openpose(root, "a", 0, [make_person(25, 1)])
    body = json.loads(path.read_text())
    body["people"][0]["pose_keypoints_2d"] = body["people"][0]["pose_keypoints_2d"][:-1]
    path.write_text(json.dumps(body))
    with pytest.raises(SceneFormatError, match=r"people\[0\]\.pose_keypoints_2d.*multiple of 3"):
        read_openpose_folders(root, ["a"])
    path.write_text('{"version": 1.3}')
    with pytest.raises(SceneFormatError, match=r"keypoints\.json: field 'people'"):
        read_openpose_folders(root, ["a"])
    path.write_text("{not json")
    with pytest.raises(SceneFormatError, match=r"keypoints\.json: not valid JSON"):
        read_openpose_folders(root, ["a"])
    path.unlink()
    (root / "a" / "keypoints.json").write_text('{"people": []}')
    with pytest.raises(SceneFormatError, match=r"keypoints\.json: field 'file name'"):
        read_openpose_folders(root, ["a"])


def test_frame_index():
    assert frame_index(Path("cam0_000000000012_keypoints.json")) == 12
    assert frame_index(Path("000123.json")) == 123
    assert frame_index(Path("video2_0007.json")) == 7


# --------------------------------------------------------------------------- bad input


def _campus_pose2sim(directory: Path) -> Path:
    rig = read_voxelpose_calibration(real_rig_path("campus"))
    return write_pose2sim_calibration(rig, directory / "Calib.toml")


def _assert_nothing_written(out_dir: Path) -> None:
    assert not out_dir.exists()
    assert not [p for p in out_dir.parent.iterdir() if p.name.startswith(f".{out_dir.name}")]


def _expect_error(out_dir: Path, *needles: str, **kwargs) -> SceneFormatError:
    with pytest.raises(SceneFormatError) as info, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        convert_scene(out_dir=out_dir, **kwargs)
    for needle in needles:
        assert needle in str(info.value), (needle, str(info.value))
    _assert_nothing_written(out_dir)
    return info.value


def _easymocap_case(tmp: Path, *, intri=EASYMOCAP_INTRI, extri=EASYMOCAP_EXTRI, size=True):
    write_easymocap_text(tmp / "em", intri, extri)
    kwargs = {"calib_format": "easymocap", "calib_paths": [tmp / "em"]}
    return kwargs | ({"image_size": (1920, 1080)} if size else {})


def _pose2sim_case(tmp: Path, edit) -> dict:
    calib = _campus_pose2sim(tmp)
    calib.write_text(edit(calib.read_text()))
    return {"calib_format": "pose2sim", "calib_paths": [calib]}


def _voxelpose_case(tmp: Path, edit) -> dict:
    raw = json.loads(real_rig_path("campus").read_text())
    edit(raw)
    (tmp / "campus.json").write_text(json.dumps(raw))
    return {"calib_format": "voxelpose", "calib_paths": [tmp / "campus.json"]}


def _no_extri(tmp: Path) -> dict:
    kwargs = _easymocap_case(tmp)
    (tmp / "em" / "extri.yml").unlink()
    return kwargs


_K_CAM3 = "K_cam3: !!opencv-matrix\r\n  rows: {}\r\n  cols: 3\r\n  dt: d\r\n  data: ["
_ROT_ONLY = EASYMOCAP_EXTRI.replace("R_cam3:", "Unused_cam3:")

# case -> (make the input under tmp_path -> convert_scene kwargs, strings the error must hold)
BAD_CALIBRATIONS = {
    "missing file": (
        lambda tmp: {"calib_format": "pose2sim", "calib_paths": [tmp / "nope.toml"]},
        ["nope.toml", "file not found"],
    ),
    "missing extri.yml": (_no_extri, ["extri.yml", "file not found"]),
    "missing field (pose2sim)": (
        lambda tmp: _pose2sim_case(
            tmp, lambda t: "\n".join(ln for ln in t.splitlines() if "translation" not in ln)
        ),
        ["Calib.toml", "'0.translation'", "missing"],
    ),
    "missing field (easymocap)": (
        lambda tmp: _easymocap_case(tmp, extri=EASYMOCAP_EXTRI.replace("T_cam3", "X_cam3")),
        ["extri.yml", "'T_cam3'", "missing"],
    ),
    "K is 2 x 3": (
        lambda tmp: _easymocap_case(
            tmp,
            intri=EASYMOCAP_INTRI.replace(
                _K_CAM3.format(3) + "800.000000, 0.000000, 640.000000, ", _K_CAM3.format(2)
            ),
        ),
        ["intri.yml", "'K_cam3'", "(3, 3), got (2, 3)"],
    ),
    "K rows x cols != data": (
        lambda tmp: _easymocap_case(
            tmp, intri=EASYMOCAP_INTRI.replace(_K_CAM3.format(3), _K_CAM3.format(1))
        ),
        ["intri.yml", "'K_cam3'", "1 x 3"],
    ),
    "matrix is 2 x 3": (
        lambda tmp: _pose2sim_case(tmp, lambda t: t.replace(", [ 0.0, 0.0, 1.0,],]", ",]", 1)),
        ["Calib.toml", "'0.matrix'", "(3, 3)"],
    ),
    "R not a rotation (voxelpose)": (
        lambda tmp: _voxelpose_case(
            tmp, lambda raw: raw["1"].update(R=(1.1 * np.array(raw["1"]["R"])).tolist())
        ),
        ["campus.json", "'1.R'", "rotation"],
    ),
    "R not a rotation (easymocap)": (
        lambda tmp: _easymocap_case(
            tmp, extri=_ROT_ONLY.replace("data: [-1.000000, 0.0", "data: [-2.000000, 0.0")
        ),
        ["extri.yml", "'Rot_cam3'", "rotation"],
    ),
    "no image size": (
        lambda tmp: _easymocap_case(tmp, size=False),
        ["intri.yml", "'H_01'", "image_size"],
    ),
}


@pytest.mark.parametrize("case", BAD_CALIBRATIONS)
def test_bad_calibration_leaves_nothing(tmp_path, case):
    make_input, needles = BAD_CALIBRATIONS[case]
    (tmp_path / "out").mkdir()
    _expect_error(tmp_path / "out" / "scene", *needles, **make_input(tmp_path))


def test_bad_detections_leave_nothing(tmp_path):
    out = tmp_path / "out" / "scene"
    (tmp_path / "out").mkdir()
    calib = _campus_pose2sim(tmp_path)
    kw = {"calib_format": "pose2sim", "calib_paths": [calib], "detections_format": "openpose"}

    # An infinite confidence.
    root = tmp_path / "op_inf"
    p = make_person(25, 1)
    p[5, 2] = np.inf
    path = write_openpose(root, "1", 4, [p])
    _expect_error(
        out, path.name, "'people[0].pose_keypoints_2d'", "finite", detections_path=root, **kw
    )

    # A folder for a camera the calibration does not have.
    root = tmp_path / "op_cam"
    write_openpose(root, "0", 0, [make_person(25, 1)])
    write_openpose(root, "cam9", 0, [make_person(25, 1)])
    _expect_error(out, "cam9", "'camera'", "not a camera", detections_path=root, **kw)

    # Unknown joint set.
    write_openpose(root := tmp_path / "op_ok", "0", 0, [make_person(25, 1)])
    err = _expect_error(
        out, "scene.json", "'joint_set'", "coco99", detections_path=root, joint_set="coco99", **kw
    )
    assert "coco17" in str(err)  # lists the known ones
    with pytest.raises(SceneFormatError, match=r"op_ok: field 'joint_set'.*coco99"):
        read_openpose_folders(root, ["0"], "coco99")

    # No camera folder at all.
    (tmp_path / "op_empty").mkdir()
    _expect_error(out, "op_empty", "no camera folders", detections_path=tmp_path / "op_empty", **kw)


def test_convert_scene_with_detections(tmp_path):
    calib = _campus_pose2sim(tmp_path)
    root = tmp_path / "op"
    write_openpose(root, "0", 0, [make_person(25, 1)])
    write_openpose(root, "2", 5, [make_person(25, 2), make_person(25, 3)])
    with pytest.warns(UserWarning, match="'1'"):
        out = convert_scene(
            calib_format="pose2sim",
            calib_paths=[calib],
            out_dir=tmp_path / "scene",
            detections_format="openpose",
            detections_path=root,
            layout="body25",
            joint_set="coco17",
            fps=30,
            name="campus-op",
        )
    scene = load_scene(out)
    assert scene.name == "campus-op" and scene.fps == 30.0 and scene.num_frames == 6
    np.testing.assert_array_equal(scene.detections.frame, [0, 5, 5])
    np.testing.assert_array_equal(scene.detections.view, [0, 2, 2])
    assert scene.meta["imported_from"]["detections"]["layout"] == "body25"

    # An existing scene is kept unless overwrite is given.
    with pytest.raises(FileExistsError):
        convert_scene(calib_format="pose2sim", calib_paths=[calib], out_dir=out)
    assert len(load_scene(out).detections) == 3
    convert_scene(calib_format="pose2sim", calib_paths=[calib], out_dir=out, overwrite=True)
    assert len(load_scene(out).detections) == 0


def test_writers_refuse_what_the_format_cannot_hold(tmp_path):
    rig = read_voxelpose_calibration(real_rig_path("campus"))
    skewed = CameraRig(
        (dataclasses.replace(rig[0], K=rig[0].K + [[0, 2.0, 0], [0, 0, 0], [0, 0, 0]]),)
    )
    with pytest.raises(SceneFormatError, match="skew"):
        write_voxelpose_calibration(skewed, tmp_path / "vp.json")
    spaced = CameraRig((dataclasses.replace(rig[0], name="cam 1"),))
    with pytest.raises(SceneFormatError, match="cam 1"):
        write_easymocap_calibration(spaced, tmp_path / "em")
    assert not (tmp_path / "vp.json").exists() and not (tmp_path / "em" / "intri.yml").exists()
    # Pose2Sim quotes such names and reads them back.
    back = read_calibration("pose2sim", [write_pose2sim_calibration(spaced, tmp_path / "c.toml")])
    assert_rigs_equal(spaced, back)
