"""``mvviz synth --motion FILE.bvh``: a synthetic scene whose people are motion capture.

The options and the run of :mod:`pipeline.synth.mocap_scene`, hooked into
``mvviz synth`` (:mod:`mvviz.cli.synth`) by ``--motion``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from pipeline.body.model import BodyModel
from pipeline.data.cameras import CameraRig
from pipeline.synth.detectors import DetectorNoise
from pipeline.synth.mocap_scene import MocapSceneConfig, write_mocap_scene


def add_motion_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group(
        "people from motion capture",
        "--motion makes the people BVH clips (e.g. sample_data/mocap/cmu131/131_01.bvh): "
        "their ground truth is the mocap skeleton's own joints (SMPL-24 slots where the "
        "skeleton has the joint, NaN elsewhere; COCO-17 keypoints), placed and turned into "
        "the floor area the rig sees; person p plays clip p mod (number of clips), repeated "
        "clips from other start frames. The detectors see the skeleton's COCO-17 points with "
        "the --noise-* model; occlusion comes from a proxy body (our model fitted to the "
        "motion). No videos. See pipeline/synth/mocap_scene.py.",
    )
    g.add_argument(
        "--motion", type=Path, action="append", default=None, metavar="BVH",
        help="a BVH clip (repeat for more clips); --people sets how many people play them",
    )  # fmt: skip
    g.add_argument(
        "--render-scale", type=float, default=0.5,
        help="size of the occlusion z-buffer relative to the image (with --motion; default 0.5)",
    )  # fmt: skip


def run_motion(
    args: argparse.Namespace, rig: CameraRig, model: BodyModel, noise: DetectorNoise
) -> int:
    if getattr(args, "joint_set", "coco17") != "coco17":
        raise SystemExit("mvviz synth: --motion scenes are coco17 (the mocap skeleton's points)")
    config = MocapSceneConfig(
        motions=tuple(str(m) for m in args.motion),
        num_people=args.people,
        num_frames=args.frames,
        fps=args.fps,
        seed=args.seed,
        noise=noise,
        render_scale=args.render_scale,
    )
    t0 = time.perf_counter()
    out = write_mocap_scene(args.out_dir, rig, model, config, overwrite=args.overwrite)
    print(
        f"wrote {out} ({args.people} people from {len(args.motion)} clip(s), {args.frames} "
        f"frames, {len(rig)} cameras, coco17, no video) in {time.perf_counter() - t0:.1f} s"
    )
    return 0
