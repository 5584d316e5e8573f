"""mvviz export-rrd: a scene and its pipeline results as a rerun recording.

Examples:

    mvviz export-rrd sample_data/shelf_synth -o shelf.rrd
    mvviz export-rrd scenes/capture -o part.rrd --frames 100:200 --no-images
    rerun shelf.rrd          # open it (or drag it into the rerun web viewer)
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import Counter
from pathlib import Path

from mvviz.cli.run import add_config_options, cached_results
from mvviz.export.rrd import DEFAULT_PLOT_JOINTS, count_entities, export_rrd


def parse_frames(spec: str) -> slice:
    """``A:B`` (either end may be left out, B excluded) -> ``slice(A, B)``; ``A`` -> one frame."""
    try:
        if ":" not in spec:
            a = int(spec)
            return slice(a, a + 1)
        a, b = spec.split(":", 1)
        return slice(int(a) if a.strip() else None, int(b) if b.strip() else None)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected A:B frame range, got {spec!r}") from None


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export-rrd",
        help="export a scene and its results as a rerun recording (.rrd)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("scene", type=Path, help="scene directory (see sample_data/README.md)")
    p.add_argument("-o", "--output", type=Path, required=True, help="recording to write (.rrd)")
    add_config_options(p)
    p.add_argument(
        "--frames", type=parse_frames, default=None, metavar="A:B", help="frames A..B-1 only"
    )
    p.add_argument("--no-images", action="store_true", help="leave out the camera images")
    p.add_argument("--image-width", type=int, default=480, help="width of logged images (px)")
    p.add_argument("--no-meshes", action="store_true", help="leave out the ground-truth meshes")
    p.add_argument("--no-bodies", action="store_true", help="leave out the fitted SMPL bodies")
    p.add_argument(
        "--mesh-cell-mm",
        type=float,
        default=25.0,
        help="decimation cell of the GT meshes and fitted bodies in mm, 0 for the full mesh "
        "(default 25)",
    )
    p.add_argument(
        "--plot-joints",
        default=",".join(DEFAULT_PLOT_JOINTS),
        help="comma-separated joints to plot per track (default: %(default)s)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    scene, results, model = cached_results(args)
    t0 = time.perf_counter()
    try:
        out = export_rrd(
            scene,
            results,
            model,
            args.output,
            frames=args.frames,
            images=not args.no_images,
            image_width=args.image_width,
            meshes=not args.no_meshes,
            bodies=not args.no_bodies,
            mesh_cell_mm=args.mesh_cell_mm or None,
            plot_joints=[j.strip() for j in args.plot_joints.split(",") if j.strip()],
        )
    except ValueError as exc:  # bad --plot-joints / --frames, or results of another scene
        print(f"mvviz export-rrd: error: {exc}", file=sys.stderr)
        return 2
    took = time.perf_counter() - t0
    counts = count_entities(out)
    groups = Counter("/".join(e.strip("/").split("/")[:2]) for e in counts)
    size = os.path.getsize(out)
    print(f"wrote {out}: {size / 1e6:.1f} MB in {took:.1f} s, {len(counts)} entities")
    for group, n in sorted(groups.items()):
        print(f"  {group:<20} {n}")
    return 0
