"""mvviz convert: turn another tool's calibration (and detections) into a native scene.

Examples:

    # the Shelf rig, cameras only
    mvviz convert --from voxelpose calibration_shelf.json -o scenes/shelf

    # an EasyMocap capture with its 2D keypoints
    mvviz convert --from easymocap data/intri.yml data/extri.yml \\
        --detections-from easymocap --detections data/annots -o scenes/capture

    # a Pose2Sim calibration with OpenPose output, one folder per camera
    mvviz convert --from pose2sim Calib.toml \\
        --detections-from openpose --detections pose/ --fps 30 -o scenes/trial
"""

from __future__ import annotations

import argparse
import functools
import sys
import warnings
from pathlib import Path

from pipeline.core.files import SceneFormatError
from pipeline.data.joint_sets import JOINT_SETS
from pipeline.data.scene import load_scene
from pipeline.evaluation.protocol import PROTOCOLS, read_protocol_gt, save_scene_protocol
from pipeline.importers import (
    CALIBRATION_FORMATS,
    DETECTION_FORMATS,
    SOURCE_LAYOUTS,
    convert_scene,
)

_EPILOG = """\
calibration formats (CALIB_FILES):
{calib}

detection formats (--detections DIR):
{det}

Camera names come from the calibration; detection folders must be named like the
cameras (a folder for an unknown camera is an error, a missing folder only a
warning). The keypoint layout (BODY_25, BODY_25B, OpenPose COCO-18, COCO-17,
Human3.6M-17, Halpe-26, COCO-WholeBody-133, BlazePose-33, SMPL-24) is identified from
the data: counts collide (25: BODY_25 / BODY_25B; 17: COCO / Human3.6M), so every
candidate is scored on anatomy over all detections (vertical body order, mid-points,
left/right pairs agreeing; left vs right from the people facing the camera), and a
file whose evidence is weak is refused: name its layout with --layout. The decision and
its evidence are printed and stored in scene.json. The scene keeps the layout's joints
(COCO-WholeBody: body and feet, coco23) unless --joint-set converts them by name.
Metres are converted to millimetres. Nothing is written unless everything reads
cleanly; the exit code is 2 on bad input.
"""


def register(subparsers) -> None:
    """Add the ``convert`` subcommand to ``subparsers``."""
    calib = "\n".join(f"  {f.name:<10} {f.files}" for f in CALIBRATION_FORMATS.values())
    det = "\n".join(f"  {f.name:<10} {f.files}" for f in DETECTION_FORMATS.values())
    parser = subparsers.add_parser(
        "convert",
        help="convert another tool's calibration (and 2D detections) into a scene directory",
        description=__doc__,
        epilog=_EPILOG.format(calib=calib, det=det),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--from",
        dest="calib_format",
        required=True,
        choices=sorted(CALIBRATION_FORMATS),
        help="format of the calibration files",
    )
    parser.add_argument(
        "calib_files",
        nargs="+",
        metavar="CALIB_FILES",
        help="calibration file(s): see the list of formats below",
    )
    parser.add_argument(
        "--detections-from",
        dest="detections_format",
        choices=sorted(DETECTION_FORMATS),
        help="format of the 2D detections (requires --detections)",
    )
    parser.add_argument(
        "--detections",
        metavar="DIR",
        help="directory with one folder of per-frame json files per camera",
    )
    parser.add_argument(
        "--joint-set",
        default=None,
        choices=sorted(JOINT_SETS),
        help="joint set of the scene's keypoints (default: the detections' own layout)",
    )
    parser.add_argument(
        "--layout",
        choices=sorted(SOURCE_LAYOUTS),
        help="the detection files' keypoint layout, instead of identifying it from the data",
    )
    parser.add_argument(
        "--fps", type=float, default=25.0, help="frame rate of the scene (default: %(default)s)"
    )
    parser.add_argument("--name", help="scene name (default: the output directory's name)")
    parser.add_argument(
        "--image-size",
        nargs=2,
        type=int,
        metavar=("W", "H"),
        help="image size in pixels, for calibrations that do not store it "
        "(EasyMocap without H_/W_, VoxelPose rigs other than Shelf and Campus)",
    )
    parser.add_argument(
        "--reference",
        action="append",
        default=[],
        metavar="NAME=FILE.trc",
        help="attach another tool's 3D result (a Pose2Sim / OpenSim TRC: metres, Y up) as "
        "reference track NAME, drawn beside ours in the viewer (repeatable)",
    )
    add_protocol_options(parser)
    parser.add_argument(
        "--overwrite", action="store_true", help="replace SCENE_DIR if it exists and is not empty"
    )
    parser.add_argument(
        "-o", "--output", required=True, metavar="SCENE_DIR", help="scene directory to write"
    )
    parser.set_defaults(func=functools.partial(run, parser=parser))


def add_protocol_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--protocol-gt",
        metavar="FILE",
        type=Path,
        help="the Shelf / Campus protocol's truth (actorsGT.mat, or an npz of frame, person_id, "
        "joints3d mm), stored in the scene for `mvviz eval --protocol` and the viewer's "
        "failure review",
    )
    parser.add_argument(
        "--protocol", choices=PROTOCOLS, default="shelf",
        help="which protocol --protocol-gt follows (default: %(default)s)",
    )  # fmt: skip


def run(args: argparse.Namespace, *, parser: argparse.ArgumentParser) -> int:
    """Convert; returns the exit code (format errors propagate to ``mvviz.cli.main``)."""
    if (args.detections_format is None) != (args.detections is None):
        parser.error("--detections-from and --detections go together")
    # the truth is read and checked before anything is written
    truth = read_protocol_gt(args.protocol_gt) if args.protocol_gt is not None else None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            out = _convert(args)
        finally:
            for w in caught:
                print(f"mvviz convert: warning: {w.message}", file=sys.stderr)
    if truth is not None:
        save_scene_protocol(out, args.protocol, truth)
        print(f"stored the {args.protocol} protocol's truth: {len(truth.frame)} actor-frames")
    scene = load_scene(out)
    det = scene.detections
    imported = scene.meta.get("imported_from", {}).get("detections", {})
    layout = imported.get("layout")
    for line in (imported.get("layout_decision") or {}).get("evidence", []):
        print(f"layout: {line}")
    print(
        f"wrote {out}: {len(scene.rig)} cameras ({', '.join(scene.rig.names)}), "
        f"{len(det)} detections in {scene.num_frames} frames"
        + (f" ({layout} -> {scene.joint_set.name})" if layout else "")
    )
    return 0


def _convert(args: argparse.Namespace):
    return convert_scene(
        calib_format=args.calib_format,
        calib_paths=args.calib_files,
        out_dir=args.output,
        detections_format=args.detections_format,
        detections_path=args.detections,
        joint_set=args.joint_set,
        layout=args.layout,
        fps=args.fps,
        name=args.name,
        image_size=tuple(args.image_size) if args.image_size else None,
        overwrite=args.overwrite,
        references=parse_references(args.reference),
    )


def parse_references(specs: list[str]) -> dict[str, str]:
    """``["NAME=FILE", ...]`` -> ``{NAME: FILE}``; a bad or repeated NAME is a SceneFormatError."""
    out: dict[str, str] = {}
    for spec in specs:
        name, sep, path = spec.partition("=")
        if not sep or not name or not path:
            raise SceneFormatError(spec, "--reference", "expected NAME=FILE.trc")
        if name in out:
            raise SceneFormatError(spec, "--reference", f"reference {name!r} given twice")
        out[name] = path
    return out
