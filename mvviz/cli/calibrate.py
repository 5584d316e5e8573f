"""mvviz calibrate: calibrate cameras from footage of a ChArUco board or a checkerboard.

Examples:

    # four synchronised videos of a ChArUco board (Caliscope's board file and sync table)
    mvviz calibrate cam_0.mp4 cam_1.mp4 cam_2.mp4 cam_3.mp4 --board charuco.toml \\
        --sync timestamps.csv -o calibration/

    # folders of images, a checkerboard of 9x6 squares of 25 mm, the board on the floor
    # in frame 12 (world: z up, origin on the board, mm)
    mvviz calibrate cams/left cams/right --board checkerboard:9x6:0.025 --floor-frame 12 -o out/

    # keep known intrinsics, solve the poses only
    mvviz calibrate cam_*.mp4 --board charuco:4x5:0.054:0.0405:DICT_4X4_1000:inverted \\
        --intrinsics camera_array.toml -o out/
"""

from __future__ import annotations

import argparse
import functools
import math
import sys
import warnings
from pathlib import Path

from pipeline.calibrate.board import SPEC_HELP, parse_board
from pipeline.calibrate.calibrate import calibrate_cameras, write_calibration
from pipeline.core.files import SceneFormatError
from pipeline.importers import CALIBRATION_FORMATS, read_calibration
from pipeline.importers.calibration import read_caliscope_calibration

_EPILOG = """\
Each camera is a video or a folder of images; its name is the file's stem or the folder's
name. Frames are matched across cameras by index, or by --sync (sync_index, cam_id,
frame_index, frame_time; cam_id = the camera's position on the command line).

Writes OUT/cameras.json (mvviz's own: mm, OpenCV world-to-camera), OUT/Calib.toml
(Pose2Sim: metres, k1 k2 p1 p2) and OUT/calibration_report.html (per camera: the figures,
the board corners over the image coloured by their reprojection error). The world is
the first calibrated camera's frame, or with --floor-frame N the board as seen in frame N
laid on the floor (z up, mm). The board moves while it is filmed: the bundle adjustment
sees it where it was when each camera took its frame, and estimates each camera's time
offset (frames; ms with --sync's frame_time; + = taken later than matched), relative to
the first camera. A camera that cannot be calibrated is named with the reason and left
out; no board at all, or no two cameras seeing it together, is an error (exit 2, nothing
written).
"""


def register(subparsers) -> None:
    """Add the ``calibrate`` subcommand to ``subparsers``."""
    parser = subparsers.add_parser(
        "calibrate",
        help="calibrate cameras from footage of a ChArUco board or checkerboard",
        description=__doc__,
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("footage", nargs="+", metavar="VIDEO_OR_DIR", help="one per camera")
    parser.add_argument("--board", required=True, metavar="BOARD", help=SPEC_HELP)
    parser.add_argument("-o", "--output", required=True, metavar="OUT", help="output directory")
    parser.add_argument("--sync", metavar="CSV", help="timestamps.csv matching the frames")
    parser.add_argument(
        "--intrinsics", metavar="FILE",
        help="keep these intrinsics (a cameras.json, or any calibration format: "
        f"{', '.join(sorted(CALIBRATION_FORMATS))}; cameras matched by name, else by order)",
    )  # fmt: skip
    parser.add_argument(
        "--intrinsics-format", choices=sorted(CALIBRATION_FORMATS),
        help="format of --intrinsics (default: from the file: .json native, "
        "camera_array.toml caliscope, other .toml pose2sim)",
    )  # fmt: skip
    parser.add_argument(
        "--floor-frame", type=int, metavar="N",
        help="put the world on the board as seen in (synchronised) frame N: z up, mm",
    )  # fmt: skip
    parser.add_argument(
        "--fixed-sync", action="store_true",
        help="hold the cameras as synchronised as the frames are matched (default: estimate "
        "each camera's time offset, up to 2 frames, with the board's motion)",
    )  # fmt: skip
    parser.set_defaults(func=functools.partial(run, parser=parser))


def read_intrinsics(path: str, fmt: str | None):
    """The rig whose intrinsics to keep (its poses are not used)."""
    p = Path(path)
    if fmt is not None:
        return read_calibration(fmt, [p])
    if p.suffix == ".json":
        from pipeline.data.cameras import load_cameras

        return load_cameras(p)
    if p.suffix == ".toml":
        text = p.read_text(encoding="utf-8", errors="replace") if p.is_file() else ""
        if "[cameras." in text:
            return read_caliscope_calibration(p, require_poses=False)
        return read_calibration("pose2sim", [p])
    raise SceneFormatError(p, None, "unknown calibration format: give --intrinsics-format")


def sync_offset(report) -> str:
    """A camera's estimated time offset, e.g. ``-0.84 fr (-140 ms)``."""
    if math.isnan(report.sync_offset_frames):
        return "-"
    text = f"{round(report.sync_offset_frames, 2) + 0.0:+.2f} fr"  # + 0.0: no "-0.00"
    if not math.isnan(report.sync_offset_s):
        text += f" ({round(1000 * report.sync_offset_s) + 0.0:+.0f} ms)"
    return text


def run(args: argparse.Namespace, *, parser: argparse.ArgumentParser) -> int:
    """Calibrate and write; returns the exit code."""
    board = parse_board(args.board)
    given = (
        None
        if args.intrinsics is None
        else read_intrinsics(args.intrinsics, args.intrinsics_format)
    )
    cal = calibrate_cameras(
        args.footage, board, sync=args.sync, intrinsics=given,
        intrinsics_source=args.intrinsics or "--intrinsics", floor_frame=args.floor_frame,
        sync_offsets=not args.fixed_sync, progress=True,
    )  # fmt: skip
    print(f"{'camera':<12} {'frames':>7} {'board':>6} {'intr.':>6} {'intr. RMS':>10} {'BA RMS':>8} "
          f"{'sync offset':>20}")  # fmt: skip
    for r in cal.reports:
        rms = (
            "given"
            if math.isnan(r.intrinsic_rms) and r.problem is None
            else f"{r.intrinsic_rms:.3f}"
        )
        print(
            f"{r.name:<12} {r.frames:>7} {r.board_frames:>6} {r.intrinsic_views:>6} "
            f"{rms:>10} {r.ba_rms:>8.3f} {sync_offset(r):>20}"
        )
    for r in cal.reports:
        if abs(r.sync_offset_frames) >= 0.5:
            when = "earlier" if r.sync_offset_frames < 0 else "later"
            ms = "" if math.isnan(r.sync_offset_s) else f" ({abs(1000 * r.sync_offset_s):.0f} ms)"
            ref = next(x.name for x in cal.reports if x.sync_offset_frames == 0)
            print(
                f"mvviz calibrate: note: {r.name}'s frames were taken "
                f"{abs(r.sync_offset_frames):.2f} frame{ms} {when} than they are matched to "
                f"{ref}'s: modelled, but check the sync", file=sys.stderr,
            )  # fmt: skip
    for r in cal.reports:
        if r.problem:
            print(f"mvviz calibrate: {r.name} not calibrated: {r.problem}", file=sys.stderr)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        paths = write_calibration(cal, args.output)
    for w in caught:
        print(f"mvviz calibrate: note: {w.message}", file=sys.stderr)
    print(f"wrote {', '.join(map(str, paths))}: {len(cal.rig)} of {len(cal.reports)} cameras")
    return 0
