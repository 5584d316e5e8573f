"""BVH reader (pipeline/importers/bvh.py): forward kinematics against hand-computed
positions, channel orders against scipy, units and axes, the real CMU clips, and a
SceneFormatError naming file and line for every malformed input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.core.files import SceneFormatError
from pipeline.importers.bvh import (
    Y_UP_TO_WORLD,
    axis_rotation,
    bvh_to_world_mm,
    forward_kinematics,
    read_bvh,
)

REPO = Path(__file__).resolve().parents[2]
CMU = REPO / "sample_data" / "mocap" / "cmu131"
CMU_SCALE = 0.056444

TINY = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT Spine
  {
    OFFSET 0 2 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT Neck
    {
      OFFSET 0 0 0
      CHANNELS 3 Xrotation Yrotation Zrotation
      End Site
      {
        OFFSET 0 1 0
      }
    }
  }
}
MOTION
Frames: 4
Frame Time: 0.04
1 2 3 0 0 0 0 0 0 0 0 0
1 2 3 90 0 0 0 0 0 0 0 0
1 2 3 0 0 0 0 0 0 90 90 0
0 0 0 0 0 0 90 0 90 0 0 0
"""


def _write(tmp_path: Path, text: str, name: str = "t.bvh") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_tiny_file_forward_kinematics_by_hand(tmp_path):
    m = read_bvh(_write(tmp_path, TINY))
    assert m.names == ("Hips", "Spine", "Neck", "Neck_end")
    assert m.parents == (-1, 0, 1, 2)
    assert m.end_site == (False, False, False, True)
    assert m.num_joints == 3 and m.num_frames == 4
    assert m.fps == pytest.approx(25.0)
    assert m.channels[0][:3] == ("Xposition", "Yposition", "Zposition")
    assert m.channels[2] == ("Xrotation", "Yrotation", "Zrotation")
    want = np.array(
        [
            # rest: root translated to (1, 2, 3), bones along +y; Neck has a zero offset
            [[1, 2, 3], [1, 4, 3], [1, 4, 3], [1, 5, 3]],
            # root Zrotation 90: +y turns to -x
            [[1, 2, 3], [-1, 2, 3], [-1, 2, 3], [-2, 2, 3]],
            # Neck "Xrotation Yrotation Zrotation" = Rx(90) @ Ry(90): (0,1,0) -> (0,0,1)
            # (the reverse product would give (0,0,1) -> (1,0,0) instead)
            [[1, 2, 3], [1, 4, 3], [1, 4, 3], [1, 4, 4]],
            # Spine "Zrotation Yrotation Xrotation" = Rz(90) @ Rx(90): (0,1,0) -> (0,0,1)
            # carried through the zero-offset Neck to its End Site
            [[0, 0, 0], [0, 2, 0], [0, 2, 0], [0, 2, 1]],
        ],
        float,
    )
    np.testing.assert_allclose(m.positions, want, atol=1e-12)


@pytest.mark.parametrize("order", ["ZYX", "XYZ", "ZXY", "YXZ"])
def test_channel_order_is_an_intrinsic_product(order):
    rng = np.random.default_rng(0)
    angles = rng.uniform(-170, 170, (5, 3))
    channels = (tuple(f"{a}rotation" for a in order),)
    _, rot = forward_kinematics(np.zeros((1, 3)), (-1,), channels, angles)
    want = Rotation.from_euler(order, angles, degrees=True).as_matrix()  # upper case: intrinsic
    np.testing.assert_allclose(rot[:, 0], want, atol=1e-12)
    for axis in "XYZ":
        r = axis_rotation(axis, 37.0)
        np.testing.assert_allclose(
            r, Rotation.from_euler(axis, 37.0, degrees=True).as_matrix(), atol=1e-12
        )


def test_three_position_channels_and_units(tmp_path):
    text = TINY.replace(
        "CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation",
        "CHANNELS 3 Zposition Xposition Yposition",
    )
    rows = "MOTION\nFrames: 1\nFrame Time: 0.01\n3 1 2 0 0 0 0 0 0\n"
    m = read_bvh(_write(tmp_path, text.split("MOTION")[0] + rows))
    np.testing.assert_allclose(m.positions[0, 0], [1, 2, 3])
    # 1 unit = 1 cm; Y up -> world (z, x, y) mm
    w = bvh_to_world_mm(m, scale_to_m=0.01)
    np.testing.assert_allclose(w[0, 0], [30, 10, 20])
    np.testing.assert_allclose(w[0, 3], [30, 10, 50])  # the End Site 3 units above
    np.testing.assert_allclose(bvh_to_world_mm(m, scale_to_m=0.01, y_up=False)[0, 0], [10, 20, 30])
    assert np.linalg.det(Y_UP_TO_WORLD) == pytest.approx(1.0)


def _cmu(name: str):
    path = CMU / name
    if not path.is_file():
        pytest.skip(f"{path} not shipped")
    return read_bvh(path)


@pytest.mark.parametrize(
    ("name", "frames"), [("131_01.bvh", 994), ("131_02.bvh", 1247), ("131_03.bvh", 1102)]
)
def test_cmu_clips_load_with_plausible_bones(name, frames):
    m = _cmu(name)
    assert m.num_frames == frames
    assert m.num_joints == 31
    assert m.fps == pytest.approx(120.0, rel=1e-4)
    w = bvh_to_world_mm(m, scale_to_m=CMU_SCALE)
    ix = m.index

    def length(a: str, b: str) -> np.ndarray:
        return np.linalg.norm(w[:, ix[a]] - w[:, ix[b]], axis=-1)

    for side in ("Left", "Right"):
        bones = {
            "thigh": (length(f"{side}Hip", f"{side}Knee"), 350, 480),
            "shank": (length(f"{side}Knee", f"{side}Ankle"), 340, 460),
            "upper arm": (length(f"{side}Shoulder", f"{side}Elbow"), 220, 330),
            "forearm": (length(f"{side}Elbow", f"{side}Wrist"), 170, 290),
        }
        for what, (d, lo, hi) in bones.items():
            assert lo < d.mean() < hi, (side, what, d.mean())
            assert d.std() < 1e-6  # rigid bones
    assert 100 < length("LeftHip", "RightHip").mean() < 220
    # Y up went to z up: the head is ~1.4-1.7 m over the feet, the feet near the floor
    head_z = w[:, ix["Head_end"], 2]
    assert 1350 < np.median(head_z) < 1800
    assert np.percentile(w[:, ix["LeftToe"], 2], 5) < 120
    # handedness kept: the person's left is left of (up x forward)
    fwd = (
        w[:, ix["LeftToe"]] - w[:, ix["LeftAnkle"]] + w[:, ix["RightToe"]] - w[:, ix["RightAnkle"]]
    )
    fwd[:, 2] = 0
    left = np.cross([0, 0, 1], fwd)
    side = ((w[:, ix["LeftHip"]] - w[:, ix["RightHip"]]) * left).sum(-1)
    assert (side > 0).mean() > 0.95


def test_cmu_arm_channel_order_differs_from_the_spine():
    # the cgspeed files list the arms' channels as Z X Y, the rest as Z Y X: read as given
    m = _cmu("131_01.bvh")
    assert m.channels[m.index["LeftElbow"]] == ("Zrotation", "Xrotation", "Yrotation")
    assert m.channels[m.index["LeftKnee"]] == ("Zrotation", "Yrotation", "Xrotation")
    assert m.channels[0] == (
        "Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation",
    )  # fmt: skip


BAD = [
    (lambda t: t.replace("HIERARCHY", "HIERARCH"), "line 1", "HIERARCHY"),
    (lambda t: t.replace("      }\n    }\n  }\n}", "      }\n    }\n  }"), "MOTION", "unbalanced"),
    (lambda t: t.replace("  }\n}\nMOTION", "  }\n}\n}\nMOTION"), "line 21", "unbalanced"),
    (
        lambda t: t.replace(
            "CHANNELS 3 Zrotation Yrotation Xrotation", "CHANNELS 3 Zrotation Yrotation"
        ),
        "line 9 (CHANNELS)",
        "count says 3",
    ),
    (
        lambda t: t.replace(
            "Zrotation Yrotation Xrotation\n    JOINT", "Zrotation Yrotation Wrotation\n    JOINT"
        ),
        "line 9 (CHANNELS)",
        "unknown channel",
    ),
    (lambda t: t.replace("OFFSET 0 2 0", "OFFSET 0 two 0"), "line 8 (OFFSET)", "expected a number"),
    (lambda t: t.replace("OFFSET 0 2 0", "OFFSET 0 2"), "line 8 (OFFSET)", "3 numbers"),
    (lambda t: t.replace("Frames: 4", "Frames: 5"), "Frames", "5"),
    (lambda t: t.replace("Frames: 4", "Frames: 3"), "line 27", "more frame rows"),
    (lambda t: t.replace("Frames: 4", "Frames: four"), "line 22 (Frames)", "integer"),
    (lambda t: t.replace("Frame Time: 0.04", "Frame Time: 0"), "line 23 (Frame Time)", "> 0"),
    (
        lambda t: t.replace("1 2 3 90 0 0 0 0 0 0 0 0", "1 2 3 90 0 0 0 0 0 0 0"),
        "line 25 (frame 1)",
        "expected 12 values",
    ),
    (
        lambda t: t.replace("1 2 3 90 0 0 0 0 0 0 0 0", "1 2 3 90 0 0 0 x 0 0 0 0"),
        "line 25 (frame 1, column 7)",
        "'x'",
    ),
    (lambda t: t.split("MOTION")[0], "MOTION", "missing MOTION"),
    (lambda t: t.replace("    OFFSET 0 2 0\n", ""), "line", "no OFFSET"),
]


@pytest.mark.parametrize(("mutate", "field", "text"), BAD)
def test_malformed_files_name_file_and_line(tmp_path, mutate, field, text):
    path = _write(tmp_path, mutate(TINY), "bad.bvh")
    with pytest.raises(SceneFormatError) as exc:
        read_bvh(path)
    msg = str(exc.value)
    assert str(path) in msg and field in msg and text in msg, msg


def test_missing_and_binary_files(tmp_path):
    with pytest.raises(SceneFormatError, match="file not found"):
        read_bvh(tmp_path / "nope.bvh")
    p = tmp_path / "bin.bvh"
    p.write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(SceneFormatError, match="not a text file"):
        read_bvh(p)
