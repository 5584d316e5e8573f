"""Tests of pipeline.importers.qualisys: the Qualisys ``.qca.txt`` reader and writer, and
the shipped ``sample_data/pose2sim_demo`` scene built from Pose2Sim's demo.

Units: world millimetres; Qualisys intrinsics are in 1/64 pixel, its transform in mm.
"""

from __future__ import annotations

import re
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
from pipeline.data.scene import load_scene
from pipeline.importers import (
    CALIBRATION_FORMATS,
    convert_scene,
    read_calibration,
    read_pose2sim_calibration,
    read_qualisys_calibration,
    write_qualisys_calibration,
)
from pipeline.importers.qualisys import resize_camera

DEMO = Path(__file__).resolve().parents[2] / "sample_data" / "pose2sim_demo"

# Three cameras in the structure QTM and Pose2Sim write (attribute order as in the demo):
# A looks horizontally along world +y, B straight down with a cropped video window and no
# radialDistortion3, C is a marker-only camera (skipped).
QCA = """<?xml version='1.0' encoding='ASCII'?>
<calibration created="2024-01-01" qtm-version="2023.1" source="test.qca" type="regular">
  <results min-max-diff="0." std-dev="0."/>
  <cameras>
    <camera active="1" avg-residual="0.4" model="none" point-count="100" serial="A" \
viewrotation="0">
      <fov_marker bottom="479" left="0" right="639" top="0"/>
      <fov_marker_max bottom="479" left="0" right="639" top="0"/>
      <fov_video bottom="479" left="0" right="639" top="0"/>
      <fov_video_max bottom="479" left="0" right="639" top="0"/>
      <transform r11="1" r12="0" r13="0" r21="0" r22="0" r23="1" r31="0" r32="-1" r33="0" \
x="1000" y="-2000" z="1500"/>
      <intrinsic centerPointU="20480" centerPointV="15360" focalLengthU="64000" \
focalLengthV="64640" focallength="5.5" radialDistortion1="-0.1" radialDistortion2="0.05" \
radialDistortion3="0.01" sensorMaxU="40959" sensorMaxV="30719" sensorMinU="0" sensorMinV="0" \
skew="0" tangentalDistortion1="0.001" tangentalDistortion2="-0.002"/>
    </camera>
    <camera active="1" avg-residual="0.5" model="Miqus Video" point-count="100" serial="B" \
viewrotation="0">
      <fov_video bottom="799" left="64" right="1087" top="32"/>
      <fov_video_max bottom="1087" left="0" right="1919" top="0"/>
      <transform r11="1" r12="0" r13="0" r21="0" r22="1" r23="0" r31="0" r32="0" r33="1" \
x="0" y="0" z="3000"/>
      <intrinsic centerPointU="38912" centerPointV="26624" focalLengthU="76800" \
focalLengthV="76800" radialDistortion1="0" radialDistortion2="0" skew="0" \
tangentalDistortion1="0" tangentalDistortion2="0"/>
    </camera>
    <camera active="1" avg-residual="0.3" model="Oqus 300+" point-count="100" serial="M" \
viewrotation="0">
      <fov_video bottom="1023" left="0" right="1279" top="0"/>
      <transform r11="1" r12="0" r13="0" r21="0" r22="1" r23="0" r31="0" r32="0" r33="1" \
x="0" y="0" z="3000"/>
      <intrinsic centerPointU="40960" centerPointV="32768" focalLengthU="64000" \
focalLengthV="64000" radialDistortion1="0" radialDistortion2="0" skew="0" \
tangentalDistortion1="0" tangentalDistortion2="0"/>
    </camera>
  </cameras>
</calibration>
"""

# Pose2Sim 0.10.49's own conversion of the demo's Calib.qca.txt (its calibration.py
# calib_qca_fun + toml_write, run on the shipped file): translations in metres.
POSE2SIM_DEMO_TOML = """\
[cam01]
name = "cam01"
size = [ 1088.0, 1920.0]
matrix = [ [ 1681.244873046875, 0.0, 532.97369384375], [ 0.0, 1681.075439453125, \
948.137390140625], [ 0.0, 0.0, 1.0]]
distortions = [ -0.000721609375, 0.002187234375, 9.5e-06, 1.078125e-05]
rotation = [ 1.6882754799999993, 1.0483220499999997, -0.41955852000000016]
translation = [ 0.3211048899999996, 0.9563320600000009, 2.8907130499999996]
fisheye = false

[cam02]
name = "cam02"
size = [ 1088.0, 1920.0]
matrix = [ [ 1673.729614265625, 0.0, 534.494567875], [ 0.0, 1673.79724121875, \
963.225891109375], [ 0.0, 0.0, 1.0]]
distortions = [ -0.000747609375, 0.00213728125, 1.51875e-05, 4.546875e-06]
rotation = [ 1.34975875, 1.5963809099999993, -1.1983285799999999]
translation = [ -0.11152829000000014, 0.7766184800000001, 3.0675519599999994]
fisheye = false

[cam03]
name = "cam03"
size = [ 1088.0, 1920.0]
matrix = [ [ 1681.598388671875, 0.0, 513.20837403125], [ 0.0, 1681.509887703125, \
955.005126953125], [ 0.0, 0.0, 1.0]]
distortions = [ -0.000729765625, 0.00215034375, -8.46875e-06, -8.078125e-06]
rotation = [ 0.8109654899999995, -2.1972129299999996, 1.3760277799999996]
translation = [ -0.7934803899999995, 0.32283594000000126, 4.353514870000001]
fisheye = false

[cam04]
name = "cam04"
size = [ 1088.0, 1920.0]
matrix = [ [ 1675.234985359375, 0.0, 540.106201171875], [ 0.0, 1675.204223640625, \
964.0302734375], [ 0.0, 0.0, 1.0]]
distortions = [ -0.000744265625, 0.002104171875, 4.328125e-06, 3.109375e-06]
rotation = [ 1.4045571699999995, -1.3887412699999993, 0.42535743000000026]
translation = [ 0.5030217200000007, 0.04894934000000107, 4.406564460000002]
fisheye = false

[metadata]
adjusted = false
error = 0.0
"""


def write_qca(directory: Path, text: str = QCA, name: str = "Calib.qca.txt") -> Path:
    path = directory / name
    path.write_text(text)
    return path


def read_quietly(path: Path, **kwargs) -> CameraRig:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_qualisys_calibration(path, **kwargs)


def assert_rigs_equal(a: CameraRig, b: CameraRig, atol: float = 1e-6) -> None:
    assert a.names == b.names
    for ca, cb in zip(a, b, strict=True):
        assert (ca.width, ca.height) == (cb.width, cb.height), ca.name
        for key in ("K", "dist", "R", "t"):
            np.testing.assert_allclose(
                getattr(cb, key), getattr(ca, key), atol=atol, rtol=0, err_msg=f"{ca.name} {key}"
            )


def demo_path(name: str) -> Path:
    path = DEMO / name
    if not path.exists():
        pytest.skip(f"{path} not available")
    return path


# --------------------------------------------------------------------------- hand-written


def test_hand_written_file(tmp_path):
    with pytest.warns(UserWarning, match=r"skipped.*M \(model 'Oqus 300\+'\)"):
        rig = read_qualisys_calibration(write_qca(tmp_path))
    assert rig.names == ["A", "B"]  # serials, file order; the marker camera M is skipped

    a = rig[0]
    assert (a.width, a.height) == (640, 480)  # right - left + 1, bottom - top + 1
    # 64000 / 64, 64640 / 64; 20480 / 64, 15360 / 64.
    np.testing.assert_array_equal(a.K, [[1000, 0, 320], [0, 1010, 240], [0, 0, 1]])
    # Dimensionless, used as they are: k1, k2, p1, p2, k3.
    np.testing.assert_array_equal(a.dist, [-0.1, 0.05, 0.001, -0.002, 0.01])
    # Camera axes x = +x, y = +z, z = -y (Qualisys: image y up, looking along -z), so
    # OpenCV's y (down) = -z and z (forward) = +y: the camera looks along world +y.
    np.testing.assert_array_equal(a.R, [[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    np.testing.assert_allclose(a.center, [1000, -2000, 1500], atol=1e-12)
    np.testing.assert_allclose(a.t, [-1000, 1500, 2000], atol=1e-12)  # -R @ centre
    np.testing.assert_allclose(a.project(np.array([1000.0, 1000.0, 1500.0])), [320, 240])
    # 3 m ahead, 300 mm up: y_n = -0.1, r2 = 0.01, radial = 1 - 0.001 + 0.000005 + 1e-8,
    # y_d = -0.1 * radial + p1 (r2 + 2 y^2) = -0.099900501 + 0.00003; x_d = p2 r2 = -0.00002.
    u, v = a.project(np.array([1000.0, 1000.0, 1800.0]))
    assert u == pytest.approx(320 + 1000 * -0.00002, abs=1e-9)
    assert v == pytest.approx(240 + 1010 * (-0.1 * 0.99900501 + 0.00003), abs=1e-9)

    b = rig[1]
    assert (b.width, b.height) == (1024, 768)  # 1087 - 64 + 1, 799 - 32 + 1
    # The sensor's principal point (608, 416) in the window starting at (64, 32).
    np.testing.assert_array_equal(b.K, [[1200, 0, 544], [0, 1200, 384], [0, 0, 1]])
    np.testing.assert_array_equal(b.dist, np.zeros(5))  # radialDistortion3 absent -> 0
    # The identity is a camera looking straight down, image up = world +y.
    np.testing.assert_array_equal(b.R, np.diag([1.0, -1.0, -1.0]))
    np.testing.assert_allclose(b.t, [0, 0, 3000])
    np.testing.assert_allclose(b.project(np.array([[0.0, 0, 0], [300, 600, 0]])), [
        [544, 384], [544 + 120, 384 - 240]
    ])  # fmt: skip


def _with_rotation(text: str, M: np.ndarray) -> str:
    old = 'r11="1" r12="0" r13="0" r21="0" r22="0" r23="1" r31="0" r32="-1" r33="0"'
    new = " ".join(f'r{i + 1}{j + 1}="{float(M[i, j])!r}"' for i in range(3) for j in range(3))
    return text.replace(old, new, 1)


def test_pose2sim_steps_on_a_general_rotation(tmp_path):
    """Pose2Sim's calib_qca_fun, step by step (transpose, invert, rotate pi about x)."""
    M = Rotation.from_euler("zyx", [40, -25, 70], degrees=True).as_matrix()
    rig = read_quietly(write_qca(tmp_path, _with_rotation(QCA, M)))
    centre = np.array([1000.0, -2000.0, 1500.0])
    R_q = M.T  # read_qca: r11..r33 "by-column to by-line"
    r, t = R_q.T, -R_q.T @ centre  # world_to_camera_persp
    flip = np.diag([1.0, -1.0, -1.0])  # rotate_cam(ang_x=pi)
    np.testing.assert_allclose(rig[0].R, flip @ r, atol=1e-12)
    np.testing.assert_allclose(rig[0].t, flip @ t, atol=1e-9)


def test_demo_matches_pose2sim_own_conversion(tmp_path):
    """The shipped Calib.qca.txt read here equals Pose2Sim's Calib.toml of it, to 1e-6 (mm),
    except the distortion, which Pose2Sim divides by 64 and this reader does not."""
    (tmp_path / "Calib.toml").write_text(POSE2SIM_DEMO_TOML)
    theirs = read_pose2sim_calibration(tmp_path / "Calib.toml")
    ours = read_qualisys_calibration(demo_path("Calib.qca.txt"))
    assert ours.names == theirs.names == ["cam01", "cam02", "cam03", "cam04"]
    for a, b in zip(ours, theirs, strict=True):
        assert (a.width, a.height) == (b.width, b.height) == (1088, 1920)
        np.testing.assert_allclose(a.K, b.K, atol=1e-6, rtol=0)
        np.testing.assert_allclose(a.R, b.R, atol=1e-6, rtol=0)
        np.testing.assert_allclose(a.t, b.t, atol=1e-6, rtol=0)
        np.testing.assert_allclose(a.dist[:4], 64 * b.dist[:4], rtol=1e-9)
        assert a.dist[4] == 0


# --------------------------------------------------------------------------- round trips


def _rig_strategy():
    unit = st.floats(-1.0, 1.0, allow_nan=False)
    camera = st.fixed_dictionaries(
        {
            "quat": st.tuples(unit, unit, unit, unit).filter(lambda q: np.linalg.norm(q) > 0.1),
            "t": st.tuples(*[st.floats(-2e4, 2e4, allow_nan=False)] * 3),
            "f": st.floats(50.0, 1e4),
            "aspect": st.floats(0.5, 2.0),
            "c": st.tuples(st.floats(-100, 4000), st.floats(-100, 4000)),
            "size": st.tuples(st.integers(1, 8000), st.integers(1, 8000)),
            "dist": st.tuples(*[st.floats(-1.0, 1.0, allow_nan=False)] * 5),
        }
    )
    names = st.lists(
        st.text(st.characters(codec="utf-8", exclude_categories=("Cs", "Cc")), min_size=1),
        min_size=1,
        max_size=4,
        unique=True,
    )
    return names.flatmap(
        lambda ns: st.tuples(st.just(ns), st.lists(camera, min_size=len(ns), max_size=len(ns)))
    )


@pytest.mark.slow
@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=_rig_strategy())
def test_random_rigs_survive_round_trips(tmp_path_factory, data):
    names, params = data
    cams = []
    for name, p in zip(names, params, strict=True):
        f, (cx, cy), (w, h) = p["f"], p["c"], p["size"]
        K = [[f, 0.0, cx], [0, f * p["aspect"], cy], [0, 0, 1]]
        R = Rotation.from_quat(p["quat"]).as_matrix()
        cams.append(make_camera(name=name, width=w, height=h, K=K, dist=p["dist"], R=R, t=p["t"]))
    rig = CameraRig(tuple(cams))
    path = tmp_path_factory.mktemp("qca") / "out.qca.txt"
    write_qualisys_calibration(rig, path)
    assert_rigs_equal(rig, read_calibration("qualisys", [path]))


def test_round_trip_of_the_demo_and_through_convert_scene(tmp_path):
    rig = read_qualisys_calibration(demo_path("Calib.qca.txt"))
    path = CALIBRATION_FORMATS["qualisys"].write(rig, tmp_path / "in" / "Calib.qca.txt")
    assert_rigs_equal(rig, read_qualisys_calibration(path), atol=1e-9)
    # A directory holding one .qca.txt is accepted too.
    out = convert_scene(calib_format="qualisys", calib_paths=[path.parent], out_dir=tmp_path / "s")
    assert_rigs_equal(rig, load_scene(out).rig, atol=1e-9)


def test_writer_refuses_skew(tmp_path):
    cam = make_camera(
        name="s", width=10, height=10, K=[[5, 1, 5], [0, 5, 5], [0, 0, 1]], dist=np.zeros(5),
        R=np.eye(3), t=np.zeros(3),
    )  # fmt: skip
    with pytest.raises(SceneFormatError, match=r"x\.qca\.txt: field 's\.intrinsic\.skew'"):
        write_qualisys_calibration(CameraRig((cam,)), tmp_path / "x.qca.txt")
    assert not (tmp_path / "x.qca.txt").exists()


# --------------------------------------------------------------------------- image size


def test_image_size_scales_k(tmp_path):
    path = write_qca(tmp_path)
    full = read_quietly(path)
    half = read_quietly(path, image_size=(320, 240))
    a = half[0]
    assert (a.width, a.height) == (320, 240)
    # Pixel centres stay centres: u' = (u + 0.5) / 2 - 0.5.
    np.testing.assert_allclose(a.K, [[500, 0, 159.75], [0, 505, 119.75], [0, 0, 1]])
    np.testing.assert_array_equal(a.dist, full[0].dist)
    np.testing.assert_array_equal(a.R, full[0].R)
    # The image of a point halves about the pixel-centre grid.
    X = np.array([[1200.0, 1500.0, 1300.0], [700.0, 900.0, 1700.0]])
    np.testing.assert_allclose(a.project(X), (full[0].project(X) + 0.5) / 2 - 0.5, atol=1e-9)


def test_image_size_must_be_a_uniform_scale(tmp_path):
    path = write_qca(tmp_path)
    with pytest.raises(SceneFormatError, match=r"field 'A\.fov_video'.*640x480.*632x480"):
        read_quietly(path, image_size=(632, 480))


def test_resize_camera_round_trips():
    cam = make_camera(
        name="c", width=1088, height=1920, K=[[1681, 0, 533], [0, 1680, 948], [0, 0, 1]],
        dist=[-0.05, 0.14, 0.001, 0.0007, 0], R=np.eye(3), t=[0, 0, 1000],
    )  # fmt: skip
    back = resize_camera(resize_camera(cam, 544, 960), 1088, 1920)
    np.testing.assert_allclose(back.K, cam.K, atol=1e-12)


# --------------------------------------------------------------------------- bad input


def _replace(old: str, new: str):
    def make(tmp: Path) -> Path:
        assert old in QCA, old
        return write_qca(tmp, QCA.replace(old, new, 1))

    return make


BAD_FILES = {
    "not XML": (_replace("</calibration>", ""), [r"not valid XML"]),
    "wrong root": (
        lambda tmp: write_qca(tmp, "<?xml version='1.0'?><calib/>"),
        [r"<calibration> root element, got <calib>"],
    ),
    "no cameras": (
        lambda tmp: write_qca(tmp, "<calibration><cameras/></calibration>"),
        [r"field 'cameras'", r"no <camera>"],
    ),
    "missing transform": (
        _replace('<transform r11="1" r12="0" r13="0" r21="0" r22="0"', '<other r11="1" r12="0"'),
        [r"field 'A\.transform': missing"],
    ),
    "missing intrinsic attribute": (
        _replace('focalLengthU="64000" ', ""),
        [r"field 'A\.intrinsic\.focalLengthU': missing"],
    ),
    "missing fov_video": (
        _replace('<fov_video bottom="799"', '<fov_other bottom="799"'),
        [r"field 'B\.fov_video': missing"],
    ),
    "not a number": (
        _replace('x="1000"', 'x="1,000"'),
        [r"field 'A\.transform\.x'", r"expected a number, got '1,000'"],
    ),
    "infinite": (
        _replace('z="1500"', 'z="inf"'),
        [r"field 'A\.transform\.z'", r"finite"],
    ),
    "not a rotation": (
        _replace(
            'r11="1" r12="0" r13="0" r21="0" r22="0"', 'r11="1.2" r12="0" r13="0" r21="0" r22="0"'
        ),
        [r"field 'A\.transform \(r11\.\.r33\)'", r"rotation"],
    ),
    "a reflection": (
        _replace(
            'r11="1" r12="0" r13="0" r21="0" r22="0"', 'r11="-1" r12="0" r13="0" r21="0" r22="0"'
        ),
        [r"field 'A\.transform \(r11\.\.r33\)'", r"det"],
    ),
    "zero focal length": (
        _replace('focalLengthU="64000"', 'focalLengthU="0"'),
        [r"field 'A\.intrinsic'", r"fx, fy > 0"],
    ),
    "empty video window": (
        _replace('right="1087" top="32"', 'right="63" top="32"'),
        [r"field 'B\.fov_video'", r"right >= left"],
    ),
    "view rotation": (
        _replace('serial="B" viewrotation="0"', 'serial="B" viewrotation="90"'),
        [r"field 'B\.viewrotation'", r"not supported"],
    ),
    "skew": (
        _replace(
            'focalLengthV="76800" radialDistortion1="0" radialDistortion2="0" skew="0"',
            'focalLengthV="76800" radialDistortion1="0" radialDistortion2="0" skew="3"',
        ),
        [r"field 'B\.intrinsic\.skew'"],
    ),
    "repeated serial": (
        _replace('serial="B"', 'serial="A"'),
        [r"field 'cameras'", r"unique.*'A'"],
    ),
}


@pytest.mark.parametrize("case", BAD_FILES)
def test_bad_input_names_file_and_field(tmp_path, case):
    make, needles = BAD_FILES[case]
    path = make(tmp_path)
    with pytest.raises(SceneFormatError) as info, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        convert_scene(calib_format="qualisys", calib_paths=[path], out_dir=tmp_path / "out")
    assert str(info.value).startswith(str(path))
    for needle in needles:
        assert re.search(needle, str(info.value)), (needle, str(info.value))
    assert not (tmp_path / "out").exists()


def test_missing_file_and_undeclared_bytes(tmp_path):
    with pytest.raises(SceneFormatError, match=r"nope\.qca\.txt: file not found"):
        read_qualisys_calibration(tmp_path / "nope.qca.txt")
    # QTM writes user text in the local code page under an ASCII declaration.
    path = tmp_path / "latin1.qca.txt"
    path.write_bytes(QCA.replace('created="2024-01-01"', 'created="Jos\xe9"').encode("latin-1"))
    assert read_quietly(path).names == ["A", "B"]


def test_cli_convert(tmp_path, capsys):
    from mvviz.cli import main  # the CLI is tested end to end once

    path = write_qca(tmp_path)
    out = tmp_path / "scene"
    assert main(["convert", "--from", "qualisys", str(path), "-o", str(out)]) == 0
    captured = capsys.readouterr()
    assert "2 cameras (A, B)" in captured.out and "skipped" in captured.err
    assert main(["convert", "--from", "qualisys", str(path), "--image-size", "1", "2",
                 "-o", str(tmp_path / "bad")]) == 2  # fmt: skip
    assert "A.fov_video" in capsys.readouterr().err


# --------------------------------------------------------------------------- shipped demo


def _video_info(path: Path) -> tuple[int, int, int]:
    cap = cv2.VideoCapture(str(path))
    ok, frame = cap.read()
    assert ok, path
    count = 1
    while cap.grab():
        count += 1
    return frame.shape[1], frame.shape[0], count


def test_demo_scene_loads_with_matching_videos():
    scene = load_scene(demo_path("scene.json").parent)
    assert scene.name == "pose2sim_demo" and scene.fps == 60.0 and scene.num_frames == 100
    assert scene.joint_set.name == "coco17"
    assert scene.rig.names == ["cam01", "cam02", "cam03", "cam04"]
    assert sorted(scene.videos) == scene.rig.names
    for cam in scene.rig:
        assert _video_info(scene.videos[cam.name]) == (cam.width, cam.height, scene.num_frames)
    # cameras.json is the Qualisys file read at the video size.
    qca = read_qualisys_calibration(DEMO / "Calib.qca.txt", image_size=(544, 960))
    assert_rigs_equal(qca, scene.rig, atol=1e-9)
    assert "BSD 3-Clause" in demo_path("LICENSE-pose2sim.txt").read_text()


def test_demo_cameras_look_at_one_capture_volume():
    rig = load_scene(demo_path("scene.json").parent).rig
    centres, axes = rig.centers, np.stack([cam.R[2] for cam in rig])  # optical axes, world
    # The point nearest to all four optical axes (least squares) ...
    P = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    X = np.linalg.solve(P.sum(0), np.einsum("vij,vj->i", P, centres))
    # ... is within 1 m of every axis, in front of every camera, above the floor
    distances = np.linalg.norm(np.einsum("vij,vj->vi", P, X - centres), axis=1)
    assert distances.max() < 1000.0, distances
    assert np.all(np.einsum("vi,vi->v", X - centres, axes) > 1000.0)
    assert 0 < X[2] < 2000
    # ... and projects inside every image; image "down" is world down (-z) for all.
    for cam in rig:
        u, v = cam.project(X)
        assert 0 <= u < cam.width and 0 <= v < cam.height, cam.name
        assert cam.R[1, 2] < -0.7, cam.name


def _cap_centroids(path: Path) -> np.ndarray:
    """(num_frames, 3): centroid x, y and area (px) of the largest blue-cap blob per frame."""
    cap, out = cv2.VideoCapture(str(path)), []
    while True:
        ok, image = cap.read()
        if not ok:
            return np.array(out)
        mask = cv2.inRange(cv2.cvtColor(image, cv2.COLOR_BGR2HSV), (88, 170, 70), (100, 255, 255))
        mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
        n, _, stats, centroids = cv2.connectedComponentsWithStats(mask)
        k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA])) if n > 1 else 0
        out.append((*centroids[k], stats[k, cv2.CC_STAT_AREA] if k else 0))


@pytest.fixture(scope="module")
def demo_caps():
    """The demo scene and, per camera, the blue cap's centroid in every frame (see below)."""
    scene = load_scene(demo_path("scene.json").parent)
    caps = {cam.name: _cap_centroids(scene.videos[cam.name]) for cam in scene.rig}
    seen = {name: c[:, 2] > 250 for name, c in caps.items()}  # a cap, not a few stray pixels
    return scene, caps, seen


def _triangulate(rig: CameraRig, pixels: list[tuple[int, np.ndarray]]) -> np.ndarray:
    """Linear triangulation (DLT on undistorted normalised points) of [(view, (2,) px)]."""
    rows = []
    for v, uv in pixels:
        x, y = rig[v].undistort_to_normalised(uv)
        P = np.hstack([rig[v].R, rig[v].t[:, None]])
        rows += [x * P[2] - P[0], y * P[2] - P[1]]
    X = np.linalg.svd(np.array(rows))[2][-1]
    return X[:3] / X[3]


def test_demo_calibration_triangulates_a_real_point(demo_caps):
    """One man wears a blue swim cap: its centroid, found by colour in each view, is
    (nearly) one 3D point. Triangulated from the views that see it, it reprojects within
    a few pixels; any wrong convention (axis flip, transpose, sub-pixel scale) costs
    hundreds. The bound is loose because each camera sees the cap from another side (its
    centroid moves a few cm between views: several px at 3.5 m at this scale)."""
    scene, caps, seen = demo_caps
    errors, heights = [], []
    for f in range(scene.num_frames):
        views = [v for v, cam in enumerate(scene.rig) if seen[cam.name][f]]
        if len(views) < 3:
            continue
        X = _triangulate(scene.rig, [(v, caps[scene.rig[v].name][f, :2]) for v in views])
        heights.append(X[2])
        errors += [np.linalg.norm(scene.rig[v].project(X) - caps[scene.rig[v].name][f, :2])
                   for v in views]  # fmt: skip
    assert len(heights) >= 50
    assert np.median(errors) < 6.0 and np.percentile(errors, 90) < 12.0, np.round(errors, 1)
    assert 1400 < np.median(heights) < 1800  # a standing man's head, mm above z = 0


def test_demo_videos_are_in_step(demo_caps):
    """Frame i is the same instant in every view. The cap triangulated from the other views
    at frame i is compared with each view's own cap at frame i + shift; the view's constant
    offset (the side of the cap it sees) is removed first, as it would otherwise pass for
    a shift along the direction of walking. The fit is best within a frame or two of no
    shift, and a shift of 5 frames (83 ms) is clearly worse."""
    scene, caps, seen = demo_caps
    rig, n = scene.rig, scene.num_frames
    for v, cam in enumerate(rig):
        points = {}
        for f in range(n):
            views = [w for w in range(len(rig)) if w != v and seen[rig[w].name][f]]
            if len(views) >= 2:
                points[f] = _triangulate(rig, [(w, caps[rig[w].name][f, :2]) for w in views])
        by_shift = {}
        for shift in range(-8, 9):
            residuals = np.array([
                cam.project(X) - caps[cam.name][f + shift, :2]
                for f, X in points.items() if 0 <= f + shift < n and seen[cam.name][f + shift]
            ])  # fmt: skip
            residuals -= np.median(residuals, axis=0)
            by_shift[shift] = float(np.median(np.linalg.norm(residuals, axis=1)))
        best = min(by_shift, key=by_shift.get)
        assert abs(best) <= 2, (cam.name, by_shift)
        assert min(by_shift[-5], by_shift[5]) > 1.5 * by_shift[0], (cam.name, by_shift)
