"""mvviz export: a run's results in the formats other tools read (TRC, C3D, BVH,
AMASS-style SMPL npz, animated glTF).

Examples:

    mvviz export SCENE --format trc -o out/run.trc           # every track, prefixed names
    mvviz export SCENE --format trc --per-track -o out/run.trc   # out/run_track<k>.trc
    mvviz export SCENE --format c3d --stage raw --track 2 -o out/p2.c3d
    mvviz export SCENE --format bvh -o out/run.bvh           # out/run_track<k>.bvh
    mvviz export SCENE --format smpl-npz --stage smpl -o out/run.npz
    mvviz export SCENE --format glb -o out/run.glb           # every body, animated

Stages: raw (triangulation), kalman (forward filter), rts (smoother), smpl (fit),
smpl_vae (fit with the pose prior); default: the run's last (joints: rts if the config
smooths, else kalman; bodies: smpl_vae, else smpl). bvh, smpl-npz and glb need a fit.
The results are those of `mvviz run` (cached under SCENE/.mvviz/, computed if absent).
What each format holds and which tools open it: README.md, "Results out".
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from mvviz.cli.run import add_config_options, cached_results
from pipeline.exports import FORMATS, STAGES, ExportError, export_results


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export",
        help="write a run as TRC, C3D, BVH, AMASS-style SMPL npz or animated glTF",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("scene", type=Path, help="scene directory (see sample_data/README.md)")
    p.add_argument("--format", required=True, choices=FORMATS, help="file format")
    p.add_argument("-o", "--output", type=Path, required=True, help="file to write")
    p.add_argument("--stage", choices=STAGES, default=None, help="stage (default: the last)")
    p.add_argument(
        "--track", default="all", type=track_choice, metavar="all|ID", help="one track id, or all"
    )
    p.add_argument(
        "--per-track",
        action="store_true",
        help="trc/c3d: one file per track (STEM_track<k>.trc) instead of prefixed names",
    )
    add_config_options(p)
    p.set_defaults(func=run)


def track_choice(text: str) -> str:
    """``--track``: ``all`` or a track id >= 0, checked before the run is loaded."""
    if text == "all" or (text.isdigit() and int(text) >= 0):
        return text
    raise argparse.ArgumentTypeError(f"expected 'all' or a track id, got {text!r}")


def run(args: argparse.Namespace) -> int:
    scene, results, _ = cached_results(args)
    t0 = time.perf_counter()
    try:
        files = export_results(
            results,
            args.format,
            args.output,
            fps=scene.fps,
            stage=args.stage,
            track=args.track,
            per_track=args.per_track,
        )
    except ExportError as exc:
        print(f"mvviz export: error: {exc}", file=sys.stderr)
        return 2
    took = time.perf_counter() - t0
    for f in files:
        tracks = ", ".join(map(str, f.tracks))
        print(f"wrote {f.path} ({f.path.stat().st_size / 1e3:.0f} KB; tracks {tracks})")
        for note in f.notes:
            print(f"  note: {note}")
    print(f"{len(files)} file(s) in {took:.1f} s")
    return 0
