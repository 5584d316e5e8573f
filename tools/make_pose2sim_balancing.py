#!/usr/bin/env python3
"""Build ``sample_data/pose2sim_balancing/`` from Pose2Sim's real balancing trial (BSD-3).

The source folder (``../shared/data/pose2sim_balancing``, see its README) holds the
Qualisys calibration, OpenPose BODY_25B 2D of every person in each of the four cameras
(one folder ``cam_0N`` per camera, 100 frames at 60 fps), the four real videos and
Pose2Sim's own 3D of the same 2D (raw and Butterworth-filtered TRC). This tool does
what a user would do, through the product's own importers:

 1. ``convert_scene`` with the Qualisys calibration and the OpenPose folders, no
    ``--layout`` and no ``--joint-set``: the layout is identified from the data
    (BODY_25B; the decision and its evidence go into scene.json) and kept;
 2. Pose2Sim's raw and filtered results as the reference tracks ``pose2sim`` and
    ``pose2sim_butterworth`` (TRC, Y-up metres, to world millimetres);
 3. the videos as they are (cameras 1-2 are encoded 8 px narrower than calibrated: the
    detector and the viewer apply the encoder-crop rule of ``pipeline.detect.video``);
 4. beside the scene, what it came from: ``Calib.qca.txt``, the raw 2D files
    (``pose2d/``), Pose2Sim's TRC files and settings (``ref3d/``) and the licence.

The scene is written to a temporary directory and moved into place at the end.

Usage::

    python tools/make_pose2sim_balancing.py ../shared/data/pose2sim_balancing \\
        --out sample_data/pose2sim_balancing --overwrite
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.data.scene import load_scene  # noqa: E402
from pipeline.importers import convert_scene  # noqa: E402

RAW_TRC = "S00_P00_T01_BalancingTrial_0-100.trc"
FILT_TRC = "S00_P00_T01_BalancingTrial_0-100_filt_butterworth.trc"
LICENSE = "LICENSE_pose2sim_BSD-3-Clause.txt"
NOTICE = """\
Pose2Sim balancing trial (real data), from the pose2sim package, BSD-3-Clause
(see LICENSE_pose2sim_BSD-3-Clause.txt). Pose2Sim's README credits the demo data to
@aaiaueil, Universite Gustave Eiffel. Pose2Sim: https://github.com/perfanalytics/pose2sim
(D. Pagnon et al., "Pose2Sim: An open-source Python package for multiview markerless
kinematics", JOSS 2022).

Contents: Calib.qca.txt (Qualisys calibration as shipped), pose2d/cam_0N (OpenPose
BODY_25B 2D), videos/cam0N.mp4 (the real footage), ref3d/ (Pose2Sim's own triangulation
of the same 2D: raw and Butterworth-filtered TRC, and the settings used). The scene files
(scene.json, cameras.json, detections.npz, references/) were made from them by
tools/make_pose2sim_balancing.py with mvviz's own importers.
"""


def build(src: Path, out: Path, *, overwrite: bool) -> Path:
    if out.exists() and not overwrite:
        raise SystemExit(f"error: {out} exists (pass --overwrite)")
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.") as tmp:
        scene_dir = Path(tmp) / "scene"
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            convert_scene(
                calib_format="qualisys",
                calib_paths=[src / "calibration" / "Calib.qca.txt"],
                out_dir=scene_dir,
                detections_format="openpose",
                detections_path=src / "pose2d_body25b",
                references={
                    "pose2sim": src / "ref3d" / RAW_TRC,
                    "pose2sim_butterworth": src / "ref3d" / FILT_TRC,
                },
                fps=60.0,
                name="pose2sim_balancing",
            )
        for w in caught:
            print(f"warning: {w.message}")
        (scene_dir / "videos").mkdir()
        for video in sorted((src / "videos").glob("cam0*.mp4")):
            shutil.copyfile(video, scene_dir / "videos" / video.name)
        meta_path = scene_dir / "scene.json"
        meta = json.loads(meta_path.read_text())
        meta["videos"] = "videos"
        meta["imported_from"]["calibration"]["paths"] = ["Calib.qca.txt"]
        meta["imported_from"]["detections"]["path"] = "pose2d"
        meta["source"] = {
            "dataset": "Pose2Sim balancing trial (real, BSD-3-Clause, see NOTICE.txt)",
            "made_by": "tools/make_pose2sim_balancing.py",
        }
        meta_path.write_text(json.dumps(meta, indent=1) + "\n")
        shutil.copyfile(src / "calibration" / "Calib.qca.txt", scene_dir / "Calib.qca.txt")
        shutil.copytree(src / "pose2d_body25b", scene_dir / "pose2d")
        (scene_dir / "ref3d").mkdir()
        for name in (RAW_TRC, FILT_TRC, "Config_used_a948c20.toml"):
            shutil.copyfile(src / "ref3d" / name, scene_dir / "ref3d" / name)
        shutil.copyfile(src / LICENSE, scene_dir / LICENSE)
        (scene_dir / "NOTICE.txt").write_text(NOTICE)
        scene = load_scene(scene_dir)  # what was written reads back
        if out.exists():
            shutil.rmtree(out)
        scene_dir.rename(out)
    decision = scene.meta["imported_from"]["detections"]["layout_decision"]
    print(f"wrote {out}: {scene.joint_set.name}, {len(scene.detections)} detections")
    for line in decision["evidence"]:
        print(f"  layout: {line}")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("source", type=Path, help="the pose2sim_balancing data folder")
    ap.add_argument("--out", type=Path, default=Path("sample_data/pose2sim_balancing"))
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args()
    build(args.source, args.out, overwrite=args.overwrite)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
