"""mvviz diagnose: what is wrong with the capture (not the pipeline), from the data itself.

Per camera its time offset (whole and sub-frame, with a confidence; positive = that
camera's frames lag the others), its calibration against the joints the other cameras
triangulate (a camera rotated or moved is named and refined by bundle adjustment; a step
in its residual says it moved during the capture), and the floor and "up" of the world.

Examples:

    mvviz diagnose SCENE                          # print the findings
    mvviz diagnose SCENE --json out/diag.json     # and write them as JSON
    mvviz diagnose SCENE --window 300             # sync per 300 frames: drift
    mvviz diagnose SCENE --write-cameras out/cameras.json   # the refined calibration
    mvviz diagnose SCENE --fix-floor OUT_SCENE    # a copy re-expressed z-up, floor at 0

The offsets found are printed as the `--set sync.offsets=...` that applies them (to
`mvviz run`, `view`, `eval`, `compare`: each camera's 2D is re-timed before association);
diagnosing a run that applies offsets reports what is left, and the setting printed adds
it up. Nothing is written unless asked, and what is written is written atomically.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mvviz.cli.run import add_config_options, cached_results
from pipeline.core.files import SceneFormatError, atomic_write
from pipeline.data.cameras import save_cameras
from pipeline.data.scene import write_scene
from pipeline.diagnose.calibration import replace_camera
from pipeline.diagnose.floor import transform_scene
from pipeline.diagnose.report import diagnose
from pipeline.diagnose.sync import MAX_SHIFT
from pipeline.stages.retime import offsets_setting


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "diagnose",
        help="find camera sync offsets, calibration errors and a wrong floor / up axis",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("scene", type=Path, help="scene directory (see sample_data/README.md)")
    p.add_argument("--json", type=Path, default=None, help="write the findings here")
    p.add_argument("--max-shift", type=int, default=MAX_SHIFT, help="frames tried either way")
    p.add_argument("--window", type=int, default=0, help="also estimate sync per N frames")
    p.add_argument("--refine-focal", action="store_true", help="refine suspects' focal too")
    p.add_argument(
        "--write-cameras", type=Path, default=None, metavar="FILE",
        help="write cameras.json with every suspect camera refined",
    )  # fmt: skip
    p.add_argument(
        "--fix-floor", type=Path, default=None, metavar="OUT_SCENE",
        help="write a copy of the scene re-expressed z-up with the floor at 0",
    )  # fmt: skip
    add_config_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.max_shift < 1:
        raise SceneFormatError("--max-shift", None, f"expected >= 1, got {args.max_shift}")
    scene, results, model = cached_results(args)
    found = diagnose(
        scene, results, max_shift=args.max_shift, window=args.window or None,
        refine_focal=args.refine_focal,
    )  # fmt: skip
    for line in found.lines():
        print(line)
    report = found.to_json()
    late = {k: e.offset_frames for k, e in found.sync.items() if e.offset}
    if late:
        setting = offsets_setting(late, results.config.sync.by_camera())
        report["sync_apply"] = f"--set sync.offsets={setting}"
        print(f"to apply the offsets: mvviz run {args.scene} {report['sync_apply']}")
    if args.json is not None:
        with atomic_write(args.json, "w") as fh:
            json.dump(report, fh, indent=1)
        print(f"wrote {args.json}")
    if args.write_cameras is not None:
        rig = scene.rig
        for name, f in found.calibration.items():
            if f.refined is not None:
                rig = replace_camera(rig, rig.index_of(name), f.refined)
        save_cameras(rig, args.write_cameras)
        n = sum(f.refined is not None for f in found.calibration.values())
        print(f"wrote {args.write_cameras} ({n} camera(s) refined)")
    if args.fix_floor is not None:
        _write_fixed(scene, found.floor, model, args.fix_floor)
    return 0


def _write_fixed(scene, floor, model, out: Path) -> None:
    if floor is None:
        raise SceneFormatError(scene.root, None, "no floor found: nothing to fix")
    fixed = transform_scene(scene, floor.fix_transform(), model)
    videos = {k: v for k, v in scene.videos.items() if Path(v).is_file()}
    write_scene(
        out, name=fixed.name, fps=fixed.fps, num_frames=fixed.num_frames,
        joint_set=fixed.joint_set, rig=fixed.rig, detections=fixed.detections, gt=fixed.gt,
        videos=videos, references=fixed.references,
        extra_meta={"re_expressed": {"from": str(scene.root),
                                     "transform": floor.fix_transform().round(6).tolist()}},
    )  # fmt: skip
    print(f"wrote {out} (z-up, floor at 0; {len(videos)} video(s) copied)")
