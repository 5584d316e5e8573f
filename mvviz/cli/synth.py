"""``mvviz synth``: write a synthetic multi-view scene with ground truth."""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

from mvviz.cli import at_least
from mvviz.cli.synth_mocap import add_motion_options, run_motion
from pipeline.body.keypoints import FITTABLE_JOINT_SETS
from pipeline.body.model import load_body_model
from pipeline.core.files import SceneFormatError
from pipeline.core.units import SAMPLE_DATA
from pipeline.data.cameras import load_cameras
from pipeline.importers.calibration import read_voxelpose_calibration
from pipeline.synth.detectors import DetectorNoise
from pipeline.synth.rigs import dome_capture_radius, dome_rig, parse_dome_spec
from pipeline.synth.scene_gen import SynthConfig, write_synth_scene

RIGS_DIR = SAMPLE_DATA / "rigs"


def load_rig(spec: str):
    """``shelf`` / ``campus`` (the real rigs shipped in sample_data/rigs), ``dome:N`` /
    ``dome:N:RADIUS_MM`` (N HD cameras on a Panoptic-like dome,
    :func:`pipeline.synth.rigs.dome_rig`) or a cameras.json path."""
    dome = parse_dome_spec(spec)
    if dome is not None:
        return dome_rig(dome[0], radius_mm=dome[1])
    if spec.lower() in ("shelf", "campus"):
        return read_voxelpose_calibration(RIGS_DIR / f"{spec.lower()}_voxelpose.json")
    path = Path(spec)
    if path.suffix == ".json" and path.is_file():
        try:
            return load_cameras(path)
        except SceneFormatError as cameras_error:  # a VoxelPose rig file, or neither
            try:
                return read_voxelpose_calibration(path)
            except (SceneFormatError, KeyError, TypeError):
                raise cameras_error from None
    return load_cameras(path)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "synth",
        help="write a synthetic scene (rendered views, simulated detectors, ground truth)",
        description=(
            "Synthesise a native scene: people with different body shapes walk, turn, reach, "
            "crouch and wave in the area a real rig sees; each view is rendered with a z-buffer "
            "into videos/<camera>.mp4, and simulated 2D keypoint and monocular SMPL detectors "
            "fill detections.npz; gt.npz holds the truth. Deterministic for a seed."
        ),
    )
    p.add_argument("out_dir", type=Path, help="scene directory to create")
    p.add_argument(
        "--rig",
        default="shelf",
        help="shelf, campus, dome:N (N 1920x1080 cameras on a Panoptic-like dome of 4 m "
        "radius; dome:N:RADIUS_MM for another size), or a cameras.json (default: shelf)",
    )
    p.add_argument(
        "--area-radius",
        type=float,
        default=None,
        metavar="MM",
        help="people stand within this distance of the cameras' mean centre (default: the "
        "capture circle for a dome, 0.6 of its radius; else anywhere 3 cameras see)",
    )
    p.add_argument("--people", type=at_least(1), default=4)
    p.add_argument("--frames", type=at_least(1), default=250)
    p.add_argument("--fps", type=float, default=25.0)
    p.add_argument("--seed", type=int, default=0)
    add_motion_options(p)
    p.add_argument(
        "--joint-set",
        default="coco17",
        choices=FITTABLE_JOINT_SETS,
        help="layout of the ground-truth keypoints and simulated 2D detections, read off the "
        "mesh by pipeline/body/keypoints.py (default: coco17)",
    )
    p.add_argument(
        "--occlusion",
        default="auto",
        choices=("auto", "render", "proxy"),
        help="occluded keypoints from full renders, or from a coarse body at the keypoints' "
        "pixels only (~50x less CPU on dome:16 x 10, the same statistics within about a "
        "percent); auto: "
        "render with --video, proxy with --no-video (default)",
    )
    p.add_argument("--video-scale", type=float, default=1.0, help="scale of the written videos")
    p.add_argument("--no-video", action="store_true", help="skip writing videos (still renders)")
    p.add_argument("--smpl-model", default=None, help="body model file (.npz/.pkl)")
    p.add_argument("--overwrite", action="store_true")
    noise = p.add_argument_group(
        "detector noise model",
        "fields of pipeline.synth.detectors.DetectorNoise (documented there and in "
        "sample_data/README.md)",
    )
    for f in dataclasses.fields(DetectorNoise):
        noise.add_argument(
            f"--noise-{f.name.replace('_', '-')}",
            type=float,
            default=f.default,
            dest=f"noise_{f.name}",
            metavar="X",
            help=f"(default {f.default})",
        )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        rig = load_rig(args.rig)
    except SceneFormatError:
        raise
    except ValueError as exc:  # a dome spec that does not parse
        raise SceneFormatError(args.rig, "--rig", str(exc)) from None
    area_radius = args.area_radius
    dome = parse_dome_spec(args.rig)
    if area_radius is None and dome is not None:
        area_radius = dome_capture_radius(dome[1])
    model = load_body_model(args.smpl_model)
    noise = DetectorNoise(
        **{f.name: getattr(args, f"noise_{f.name}") for f in dataclasses.fields(DetectorNoise)}
    )
    if args.motion:
        return run_motion(args, rig, model, noise)
    config = SynthConfig(
        num_people=args.people,
        num_frames=args.frames,
        fps=args.fps,
        seed=args.seed,
        render_video=not args.no_video,
        video_scale=args.video_scale,
        noise=noise,
        joint_set=args.joint_set,
        area_radius_mm=area_radius,
        occlusion=args.occlusion,
    )
    t0 = time.perf_counter()
    out = write_synth_scene(args.out_dir, rig, model, config, overwrite=args.overwrite)
    print(
        f"wrote {out} ({args.people} people, {args.frames} frames, {len(rig)} cameras, "
        f"{args.joint_set}) "
        f"in {time.perf_counter() - t0:.1f} s"
    )
    return 0
