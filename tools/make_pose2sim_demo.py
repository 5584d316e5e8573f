#!/usr/bin/env python3
"""Build ``sample_data/pose2sim_demo/`` from Pose2Sim's multi-person demo (BSD-3).

Pose2Sim (https://github.com/perfanalytics/pose2sim) ships, inside its PyPI wheel, four
synchronised Qualisys video recordings of two people around a treadmill
(``Pose2Sim/Demo_MultiPerson/videos/cam01..cam04.mp4``: 100 frames, 60 fps, 1088x1920
portrait) with their Qualisys calibration (``calibration/Calib.qca.txt``). This tool:

 1. reads the calibration with :func:`pipeline.importers.read_qualisys_calibration`
    (at the calibration's resolution) and checks its camera names are the video stems;
 2. decodes every video, checks its size equals the calibration's, and reports frame
    counts and frame rates (different counts are reported and the scene is cut to the
    shortest; different frame rates are an error);
 3. downscales every frame by ``--scale`` (``cv2.INTER_AREA``), scales K to match
    (:func:`pipeline.importers.qualisys.resize_camera`: pixel centres stay centres), and
    re-encodes with OpenCV's ``mp4v``;
 4. writes the scene with :func:`pipeline.data.scene.write_scene`: coco17, no detections yet
    (run ``mvviz detect`` on it), the original ``Calib.qca.txt`` beside it, and
    ``LICENSE-pose2sim.txt`` (Pose2Sim's BSD-3 notice and where the data came from).

Usage (the data comes from the wheel; do not install pose2sim, it pulls in OpenSim)::

    pip download pose2sim==0.10.49 --no-deps -d /tmp/p2s
    unzip -q /tmp/p2s/pose2sim-0.10.49-py3-none-any.whl -d /tmp/p2s/unpacked
    python tools/make_pose2sim_demo.py /tmp/p2s/unpacked/Pose2Sim \\
        --out sample_data/pose2sim_demo --scale 0.5 --overwrite
"""

from __future__ import annotations

import argparse
import hashlib
import re
import shutil
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.core.files import atomic_write  # noqa: E402
from pipeline.data.cameras import CameraRig  # noqa: E402
from pipeline.data.joint_sets import get_joint_set  # noqa: E402
from pipeline.data.scene import Detections, load_scene, write_scene  # noqa: E402
from pipeline.importers.qualisys import read_qualisys_calibration, resize_camera  # noqa: E402

DEMO = "Demo_MultiPerson"
LICENSE_NAME = "LICENSE-pose2sim.txt"


def find_demo(pose2sim_dir: Path) -> Path:
    """The ``Demo_MultiPerson`` folder under the unpacked ``Pose2Sim`` folder (or its parent)."""
    for candidate in (pose2sim_dir / DEMO, pose2sim_dir / "Pose2Sim" / DEMO):
        if (candidate / "calibration").is_dir() and (candidate / "videos").is_dir():
            return candidate
    raise SystemExit(f"error: no {DEMO}/calibration and {DEMO}/videos under {pose2sim_dir}")


def find_license(demo: Path) -> tuple[str, str]:
    """(licence text, where it was found): the wheel's dist-info, or a source checkout."""
    package = demo.parent
    candidates = sorted(package.parent.glob("pose2sim-*.dist-info/licenses/LICENSE*"))
    candidates += sorted(package.parent.glob("pose2sim-*.dist-info/LICENSE*"))
    candidates += [package.parent / "LICENSE", package / "LICENSE"]
    for path in candidates:
        if path.is_file():
            return path.read_text(), str(path.relative_to(package.parent))
    raise SystemExit(f"error: Pose2Sim's LICENSE not found next to {package}")


def pose2sim_version(demo: Path) -> str:
    for info in demo.parent.parent.glob("pose2sim-*.dist-info"):
        match = re.match(r"pose2sim-(.+)\.dist-info", info.name)
        if match:
            return match.group(1)
    return "unknown"


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def read_frames(path: Path) -> tuple[list[np.ndarray], float]:
    """Every frame of a video (decoded, not the container's count) and its frame rate."""
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise SystemExit(f"error: cannot open {path}")
    fps = float(cap.get(cv2.CAP_PROP_FPS))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame)
    cap.release()
    return frames, fps


def encode(frames: list[np.ndarray], path: Path, fps: float, size: tuple[int, int]) -> None:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
    if not writer.isOpened():
        raise SystemExit(f"error: OpenCV cannot write mp4v to {path}")
    for frame in frames:
        if (frame.shape[1], frame.shape[0]) != size:
            frame = cv2.resize(frame, size, interpolation=cv2.INTER_AREA)
        writer.write(frame)
    writer.release()


def license_text(notice: str, notice_from: str, version: str, sources: dict[str, str]) -> str:
    files = "\n".join(f"    {name}  sha256 {digest}" for name, digest in sources.items())
    return f"""\
The videos (videos/*.mp4) and the calibration (Calib.qca.txt, and cameras.json derived
from it) of this scene come from Pose2Sim's multi-person demo:

    Pose2Sim {version}, PyPI wheel (https://pypi.org/project/pose2sim/),
    https://github.com/perfanalytics/pose2sim, by David Pagnon and contributors
    files (inside the wheel):
{files}

Changes: the videos were downscaled (cv2.INTER_AREA) and re-encoded with OpenCV's mp4v
by tools/make_pose2sim_demo.py; cameras.json is Calib.qca.txt converted to this
project's conventions with K scaled to the downscaled videos. Calib.qca.txt is unchanged.

Pose2Sim's licence ({notice_from}) follows.

{notice}"""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("pose2sim_dir", type=Path, help="the unpacked Pose2Sim package folder")
    parser.add_argument("--out", type=Path, default=Path("sample_data/pose2sim_demo"))
    parser.add_argument("--scale", type=float, default=0.5, help="video scale (default 0.5)")
    parser.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    args = parser.parse_args(argv)

    demo = find_demo(args.pose2sim_dir)
    qca = demo / "calibration" / "Calib.qca.txt"
    rig = read_qualisys_calibration(qca)
    videos = {cam: demo / "videos" / f"{cam}.mp4" for cam in rig.names}
    stems = sorted(p.stem for p in (demo / "videos").glob("*.mp4"))
    if sorted(videos) != stems:
        raise SystemExit(f"error: cameras {rig.names} are not the videos {stems}")

    # 1. Decode, check sizes against the calibration, report counts and rates.
    frames, rates = {}, {}
    for cam in rig:
        frames[cam.name], rates[cam.name] = read_frames(videos[cam.name])
        h, w = frames[cam.name][0].shape[:2]
        print(f"{cam.name}: {len(frames[cam.name])} frames, {rates[cam.name]:g} fps, {w}x{h}")
        if (w, h) != (cam.width, cam.height):
            raise SystemExit(
                f"error: {videos[cam.name]} is {w}x{h}, its calibration {cam.width}x{cam.height}"
            )
    if len(set(rates.values())) != 1:
        raise SystemExit(f"error: the videos have different frame rates {rates}")
    fps = next(iter(rates.values()))
    counts = {cam: len(f) for cam, f in frames.items()}
    num_frames = min(counts.values())
    if len(set(counts.values())) != 1:
        print(f"warning: frame counts differ {counts}; keeping the first {num_frames}")

    # 2. Downscale: the rig follows the videos.
    size = (round(rig[0].width * args.scale), round(rig[0].height * args.scale))
    scaled = CameraRig(tuple(resize_camera(cam, *size) for cam in rig))

    # 3. Re-encode, write the scene, then the licence and the source calibration.
    version = pose2sim_version(demo)
    notice, notice_from = find_license(demo)
    sources = {str(p.relative_to(demo.parent.parent)): sha256(p) for p in (qca, *videos.values())}
    js = get_joint_set("coco17")
    with tempfile.TemporaryDirectory() as tmp:
        encoded = {}
        for cam in rig.names:
            encoded[cam] = Path(tmp) / f"{cam}.mp4"
            encode(frames[cam][:num_frames], encoded[cam], fps, size)
        write_scene(
            args.out,
            name="pose2sim_demo",
            fps=fps,
            num_frames=num_frames,
            joint_set=js,
            rig=scaled,
            detections=Detections(
                frame=np.zeros(0, np.int64),
                view=np.zeros(0, np.int64),
                keypoints=np.zeros((0, js.num_joints, 3)),
            ),
            videos=encoded,
            extra_meta={
                "source": {
                    "dataset": f"Pose2Sim {version} {DEMO} (BSD-3-Clause, see {LICENSE_NAME})",
                    "calibration": "Calib.qca.txt (Qualisys), mvviz convert --from qualisys",
                    "calibration_size": [rig[0].width, rig[0].height],
                    "video_scale": args.scale,
                    "made_by": "tools/make_pose2sim_demo.py",
                }
            },
            overwrite=args.overwrite,
        )
    shutil.copyfile(qca, args.out / "Calib.qca.txt")
    with atomic_write(args.out / LICENSE_NAME, "w") as fh:
        fh.write(license_text(notice, notice_from, version, sources))

    scene = load_scene(args.out)
    for path in scene.videos.values():
        check, _ = read_frames(path)
        if len(check) != num_frames or check[0].shape[:2] != size[::-1]:
            raise SystemExit(f"error: {path} decodes to {len(check)} frames {check[0].shape}")
    total = sum(p.stat().st_size for p in args.out.rglob("*") if p.is_file())
    print(
        f"wrote {args.out}: {len(scene.rig)} cameras at {size[0]}x{size[1]}, "
        f"{scene.num_frames} frames at {scene.fps:g} fps ({scene.num_frames / scene.fps:.2f} s), "
        f"{total / 1e6:.2f} MB"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
