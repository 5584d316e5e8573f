"""TRC reader/writer (pipeline/importers/trc.py): round trips, Pose2Sim's real files, and a
SceneFormatError naming the field for every malformed input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.core.files import SceneFormatError
from pipeline.data.joint_sets import BODY25B, get_joint_set
from pipeline.importers.trc import (
    POSE2SIM_MARKERS,
    read_trc,
    trc_to_joint_set,
    trc_to_world_mm,
    world_mm_to_trc,
    write_trc,
)

REPO = Path(__file__).resolve().parents[2]
SHIPPED = REPO / "sample_data" / "pose2sim_balancing" / "ref3d"
RAW = "S00_P00_T01_BalancingTrial_0-100.trc"
FILT = "S00_P00_T01_BalancingTrial_0-100_filt_butterworth.trc"
BODY25B_MARKERS = (
    "RHip", "RKnee", "RAnkle", "RBigToe", "RSmallToe", "RHeel", "LHip", "LKnee", "LAnkle",
    "LBigToe", "LSmallToe", "LHeel", "Neck", "Head", "Nose", "RShoulder", "RElbow", "RWrist",
    "LShoulder", "LElbow", "LWrist",
)  # fmt: skip


def _trc_path(name: str) -> Path:
    for d in (SHIPPED, Path("/work/shared/data/pose2sim_balancing/ref3d")):
        if (d / name).is_file():
            return d / name
    pytest.skip(f"{name} not available")


@pytest.mark.parametrize("units", ["m", "mm"])
def test_write_read_round_trip(tmp_path, units):
    rng = np.random.default_rng(0)
    pts = rng.normal(0, 1.3, (7, 4, 3)) * (1000 if units == "mm" else 1)
    pts[2, 1] = np.nan  # a missing marker
    pts[6, 3] = np.nan  # missing at the end of the row (trailing empty cells)
    names = ["RHip", "LHip", "Neck", "LWrist"]
    path = tmp_path / "t.trc"
    write_trc(path, names, pts, rate=50.0, units=units, start_frame=3)
    t = read_trc(path)
    assert t.marker_names == tuple(names)
    assert t.units == units and t.data_rate == 50.0
    np.testing.assert_array_equal(t.frame_numbers, np.arange(3, 10))
    np.testing.assert_allclose(t.times, np.arange(7) / 50.0, atol=1e-12)
    assert np.isnan(t.points[2, 1]).all() and np.isnan(t.points[6, 3]).all()
    np.testing.assert_allclose(t.points, pts, atol=1e-9, equal_nan=True)
    assert not list(tmp_path.glob(".*.tmp"))  # atomic: no temporary left


def test_axes_round_trip_and_convention():
    """World (x, y, z) = TRC (Z, X, Y): the TRC's Y is up, our z is up."""
    rng = np.random.default_rng(1)
    world = rng.normal(0, 800, (5, 3, 3))
    trc_m = world_mm_to_trc(world, units="m")
    np.testing.assert_allclose(trc_m[..., 1], world[..., 2] / 1000)  # up
    np.testing.assert_allclose(trc_m[..., 2], world[..., 0] / 1000)
    np.testing.assert_allclose(trc_m[..., 0], world[..., 1] / 1000)
    np.testing.assert_allclose(world_mm_to_trc(world, y_up=False, units="mm"), world)


def test_write_world_then_joint_set(tmp_path):
    """World mm in BODY_25B -> TRC (Pose2Sim names, metres, Y up) -> back to world mm."""
    rng = np.random.default_rng(2)
    table = POSE2SIM_MARKERS["body25b"]
    names = list(BODY25B_MARKERS)
    world = rng.normal(0, 500, (4, len(names), 3)) + [0, 0, 1000]
    write_trc(tmp_path / "w.trc", names, world_mm_to_trc(world), rate=60.0)
    t = read_trc(tmp_path / "w.trc")
    np.testing.assert_allclose(trc_to_world_mm(t), world, atol=1e-6)
    j = trc_to_joint_set(t, "body25b")
    assert j.shape == (4, 25, 3)
    for m, name in enumerate(names):
        np.testing.assert_allclose(j[:, BODY25B.index[table[name]]], world[:, m], atol=1e-6)
    missing = [BODY25B.index[n] for n in ("left_eye", "right_eye", "left_ear", "right_ear")]
    assert np.isnan(j[:, missing]).all()
    assert np.isfinite(np.delete(j, missing, axis=1)).all()


def test_marker_tables_name_real_joints():
    for name, table in POSE2SIM_MARKERS.items():
        js = get_joint_set(name)
        assert set(table.values()) <= set(js.names), name
        assert len(set(table.values())) == len(table), f"{name}: two markers on one joint"
    assert POSE2SIM_MARKERS["body25b"]["Neck"] == "upper_neck"
    assert POSE2SIM_MARKERS["body25b"]["Head"] == "head_top"
    assert POSE2SIM_MARKERS["body25"]["Neck"] == "neck"
    assert POSE2SIM_MARKERS["halpe26"]["Hip"] == "mid_hip"
    assert POSE2SIM_MARKERS["blazepose33"]["LBigToe"] == "left_foot_index"


@pytest.mark.parametrize("name", [RAW, FILT])
def test_reads_pose2sim_balancing_trial(name):
    t = read_trc(_trc_path(name))
    assert t.marker_names == BODY25B_MARKERS
    assert t.points.shape == (100, 21, 3) and t.units == "m" and t.data_rate == 60.0
    np.testing.assert_array_equal(t.frame_numbers, np.arange(1, 101))
    np.testing.assert_allclose(t.times, np.arange(1, 101) / 60.0, atol=1e-9)
    assert np.isfinite(t.points).all()
    if name == RAW:  # the first cell, exactly as written
        assert t.points[0, 0, 0] == -0.06497214796810755
    j = trc_to_joint_set(t, "body25b")  # (100, 25, 3) world mm, z up
    med = np.median(j[:, [BODY25B.index[n] for n in ("head_top", "left_ankle", "right_ankle")]], 0)
    # an adult balancing on the left leg: top of the head ~1.6 m up, the standing
    # ankle ~0.15 m, the other foot lifted
    assert 1550 < med[0, 2] < 1700
    assert 100 < med[1, 2] < 200 and med[2, 2] > med[1, 2] + 30
    # the hips are ~170-200 mm apart (a real, metric person)
    hips = np.linalg.norm(
        j[:, BODY25B.index["left_hip"]] - j[:, BODY25B.index["right_hip"]], axis=1
    )
    assert 120 < np.median(hips) < 260


def _good_lines() -> list[str]:
    return [
        "PathFileType\t4\t(X/Y/Z)\tbad.trc",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        "30\t30\t2\t2\tm\t30\t1\t2",
        "Frame#\tTime\tRHip\t\t\tLHip\t\t",
        "\t\tX1\tY1\tZ1\tX2\tY2\tZ2",
        "",
        "1\t0.0\t1\t2\t3\t4\t5\t6",
        "2\t0.033\t1\t2\t3\t\t\t",
    ]


def test_good_lines_read(tmp_path):
    p = tmp_path / "good.trc"
    p.write_text("\n".join(_good_lines()) + "\n")
    t = read_trc(p)
    np.testing.assert_array_equal(t.points[0], [[1, 2, 3], [4, 5, 6]])
    assert np.isnan(t.points[1, 1]).all()


@pytest.mark.parametrize(
    ("edit", "field", "words"),
    [
        (lambda L: L.__setitem__(2, "30\t30\t3\t2\tm\t30\t1\t2"), "NumFrames", "3 frames"),
        (lambda L: L.append("3\t0.066\t1\t2\t3\t4\t5\t6"), "NumFrames", "3 rows"),
        (lambda L: L.__setitem__(2, "30\t30\t2\t3\tm\t30\t1\t2"), "NumMarkers", "names 2"),
        (lambda L: L.__setitem__(4, "\t\tX1\tY1\tZ1\tX2\tY2"), "coordinate labels", "got 5"),
        (lambda L: L.__setitem__(6, "1\t0.0\t1\t2\t3\t4\t5\t6\t7"), "line 7", "columns"),
        (lambda L: L.__setitem__(6, "1\t0.0\t1\tabc\t3\t4\t5\t6"), "line 7 RHip Y", "'abc'"),
        (lambda L: L.__setitem__(7, "x\t0.033\t1\t2\t3\t4\t5\t6"), "line 8 Frame#", "integer"),
        (lambda L: L.__setitem__(2, "30\t30\t2\t2\tinch\t30\t1\t2"), "Units", "'inch'"),
        (lambda L: L.__setitem__(2, "0\t30\t2\t2\tm\t30\t1\t2"), "DataRate", "positive"),
        (lambda L: L.__setitem__(1, "DataRate\tNumFrames\tNumMarkers"), "Units", "missing"),
        (lambda L: L.__setitem__(0, "Frame#\tTime"), "PathFileType", "PathFileType"),
        (lambda L: L.__setitem__(3, "Frame#\tTime\tRHip\t\t\tRHip\t\t"), "marker names", "twice"),
        (lambda L: L.__setitem__(3, "Time\tRHip\t\t\tLHip\t\t"), "Frame#", "Frame#"),
        (lambda L: L.__delitem__(slice(3, None)), "Frame#", "missing header line 4"),
    ],
)  # fmt: skip
def test_bad_input_names_the_field(tmp_path, edit, field, words):
    lines = _good_lines()
    edit(lines)
    p = tmp_path / "bad.trc"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(SceneFormatError) as err:
        read_trc(p)
    assert err.value.field == field
    assert str(p) in str(err.value) and words in str(err.value)


def test_missing_file_and_unmappable_markers(tmp_path):
    with pytest.raises(SceneFormatError, match="file not found"):
        read_trc(tmp_path / "nope.trc")
    write_trc(tmp_path / "x.trc", ["Foo", "Bar"], np.zeros((2, 2, 3)), rate=10)
    t = read_trc(tmp_path / "x.trc")
    with pytest.raises(SceneFormatError, match="none of the markers") as err:
        trc_to_joint_set(t, "body25b")
    assert err.value.field == "marker_names"
    with pytest.raises(SceneFormatError, match="no Pose2Sim marker mapping"):
        trc_to_joint_set(t, "smpl24")
    j = trc_to_joint_set(t, "coco17", markers={"Foo": "nose"})
    assert np.isfinite(j[:, 0]).all() and np.isnan(j[:, 1:]).all()


def test_write_rejects_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="shape"):
        write_trc(tmp_path / "a.trc", ["A"], np.zeros((2, 2, 3)), rate=10)
    with pytest.raises(ValueError, match="units"):
        write_trc(tmp_path / "a.trc", ["A"], np.zeros((2, 1, 3)), rate=10, units="ft")
    assert not (tmp_path / "a.trc").exists()
