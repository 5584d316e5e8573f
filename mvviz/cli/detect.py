"""``mvviz detect``: fill a scene's detections from its cameras' videos with BlazePose."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from pipeline.detect.blazepose import InterpreterMissingError
from pipeline.detect.video import DetectSettings, detect_scene
from pipeline.detect.video_crop import parse_video_crops


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "detect",
        help="detect people in a scene's videos (BlazePose, CPU, multi-person)",
        description=(
            "Run Google's BlazePose models (person detector + 33 landmarks, shipped in "
            "sample_data/models/blazepose) on every camera's video and write the scene's "
            "detections.npz: COCO-17 keypoints, all 33 landmarks, and the landmarks' metric 3D "
            "as monocular 3D joints (mono_joints3d, SMPL-24) for the 'smpl' 2D source. Videos "
            "match cameras by name (<camera>.mp4 for each camera in cameras.json). Resumable: "
            "an interrupted run keeps what it did under SCENE/.mvviz/detect/ and goes on from "
            "there. Needs the [video] extra (pip install 'mvviz[video]')."
        ),
    )
    p.add_argument("scene", type=Path, help="scene directory with cameras.json")
    p.add_argument(
        "--videos",
        nargs="+",
        required=True,
        metavar="DIR_OR_FILE",
        help="video files, or directories of them, named <camera>.<ext>",
    )
    p.add_argument(
        "--every",
        type=int,
        default=1,
        metavar="N",
        help="use every Nth video frame: scene frame k = video frame k*N, fps / N (default 1)",
    )
    p.add_argument("--max-people", type=int, default=None, metavar="N", help="per view and frame")
    p.add_argument("--max-frames", type=int, default=None, metavar="N", help="scene length cap")
    p.add_argument(
        "--min-score", type=float, default=0.5, metavar="X", help="detector score (default 0.5)"
    )
    p.add_argument(
        "--tiles",
        type=int,
        default=2,
        metavar="N",
        help="also run the person detector on overlapping windows showing people N times "
        "larger (1 = whole frame only, as MediaPipe; default 2: finds far more people 250-600 "
        "px tall, at 5 detector runs per frame)",
    )
    p.add_argument(
        "--video-scale",
        type=float,
        default=1.0,
        metavar="S",
        help="re-encode SCENE/videos/ at this scale (default 1: copy when possible)",
    )
    p.add_argument(
        "--video-crop",
        action="append",
        default=[],
        metavar="CAM=L,T,R,B",
        help="camera CAM's video is its calibrated image with L, T, R, B calibrated pixels "
        "cut from the left, top, right and bottom (then maybe scaled). Without it a video a "
        "few pixels off the calibration (at most 16 px or 1 %% on one dimension) is taken as "
        "an encoder's crop or padding at the right/bottom edge, with a warning (repeatable)",
    )
    p.add_argument("--threads", type=int, default=None, help="interpreter threads")
    p.add_argument("--overwrite", action="store_true", help="replace an existing detections.npz")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    settings = DetectSettings(
        every=args.every,
        max_people=args.max_people,
        max_frames=args.max_frames,
        min_score=args.min_score,
        tiles=args.tiles,
        num_threads=args.threads,
    )
    t0 = time.perf_counter()
    try:
        crops = parse_video_crops(args.video_crop)
        report = detect_scene(
            args.scene,
            args.videos,
            settings=settings,
            overwrite=args.overwrite,
            video_scale=args.video_scale,
            progress=not args.no_progress,
            video_crops=crops,
        )
    except (InterpreterMissingError, ValueError) as exc:
        print(f"mvviz detect: error: {exc}", file=sys.stderr)
        return 2
    took = time.perf_counter() - t0
    for cam, n in report.rows_per_camera.items():
        print(
            f"  {cam}: {n} people in {report.frames_with_people[cam]} of {report.num_frames} frames"
        )
    print(f"wrote {report.scene_dir / 'detections.npz'} in {took:.1f} s")
    return 0
