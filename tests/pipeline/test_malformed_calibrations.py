"""Malformed calibrations of every importer format (EasyMocap YAML, Pose2Sim TOML,
Qualisys .qca.txt, VoxelPose JSON) through ``mvviz convert``: exit 2, one line naming
the file and the field, nothing written, no traceback. The valid files are written by
our own writers from the real Campus rig; each case breaks one field."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

from mvviz.cli import main
from pipeline.importers import (
    read_voxelpose_calibration,
    write_easymocap_calibration,
    write_pose2sim_calibration,
    write_qualisys_calibration,
)
from tests.conftest import REPO

CAMPUS = REPO / "sample_data" / "rigs" / "campus_voxelpose.json"


@pytest.fixture(scope="module")
def valid(tmp_path_factory):
    d = tmp_path_factory.mktemp("calib")
    rig = read_voxelpose_calibration(CAMPUS)
    write_pose2sim_calibration(rig, d / "Calib.toml")
    write_easymocap_calibration(rig, d / "em")
    write_qualisys_calibration(rig, d / "Calib.qca.txt")
    return d


def _sub(text: str, pattern: str, repl: str) -> str:
    out, n = re.subn(pattern, repl, text, count=1, flags=re.S)
    assert n == 1, pattern
    return out


# (format, file to break, regex, replacement, words the one-line error must contain)
CASES = [
    ("pose2sim", "Calib.toml", r"matrix = \[[^\n]*", 'matrix = "K"', ["matrix"]),
    ("pose2sim", "Calib.toml", r"size = \[[^\n]*", "size = [ 360,]", ["size"]),
    ("pose2sim", "Calib.toml", r"rotation = \[[^\n]*", "rotation = [ 1.0, 2.0,]", ["rotation"]),
    ("pose2sim", "Calib.toml", r"translation = \[[^\n]*", 'translation = "far"', ["translation"]),
    (
        "pose2sim",
        "Calib.toml",
        r"distortions = \[[^\n]*",
        "distortions = [ nan, 0.0, 0.0, 0.0,]",
        ["distortions"],
    ),
    ("pose2sim", "Calib.toml", r"\[0\]\nname", "[0\nname", []),  # not TOML at all
    (
        "easymocap",
        "em/intri.yml",
        r"K_0: !!opencv-matrix\n   rows: 3",
        "K_0: !!opencv-matrix\n   rows: 2",
        ["K_0"],
    ),
    ("easymocap", "em/intri.yml", r"H_0: 288", "H_0: -5", ["H_0"]),
    (
        "easymocap",
        "em/extri.yml",
        r"(R_0: !!opencv-matrix.*?data: \[) [^,]*,",
        r"\1 .nan,",
        ["R_0"],
    ),
    ("qualisys", "Calib.qca.txt", r'focalLengthU="[^"]*"', 'focalLengthU="-3"', ["intrinsic"]),
    ("qualisys", "Calib.qca.txt", r'r11="[^"]*"', 'r11="x"', ["r11"]),
    ("qualisys", "Calib.qca.txt", r'<fov_video left="0"', '<fov_video left="abc"', ["fov_video"]),
    ("qualisys", "Calib.qca.txt", r"</calibration>", "", []),  # truncated XML
]


@pytest.mark.parametrize("fmt,name,pattern,repl,words", CASES)
def test_malformed_calibration(fmt, name, pattern, repl, words, valid, tmp_path, capsys):
    src = tmp_path / "in"
    shutil.copytree(valid, src)
    path = src / name
    path.write_text(_sub(path.read_text(), pattern, repl))
    target = src / "em" if fmt == "easymocap" else src / Path(name).name
    out = tmp_path / "scene"
    code = main(["convert", "--from", fmt, str(target), "-o", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    assert Path(name).name in err, err  # names the file
    low = err.lower()
    for w in words:
        assert w.lower() in low, (w, err)  # and the field
    assert not out.exists()  # nothing written


def test_the_valid_files_convert(valid, tmp_path, capsys):
    for fmt, target in (
        ("pose2sim", valid / "Calib.toml"),
        ("easymocap", valid / "em"),
        ("qualisys", valid / "Calib.qca.txt"),
    ):
        assert main(["convert", "--from", fmt, str(target), "-o", str(tmp_path / fmt)]) == 0
