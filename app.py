"""mvviz viewer: an interactive 3D debugger for multi-view, multi-person 3D pose.

Usage:
    python app.py [SCENE] [--port 8080] [--host 127.0.0.1 [--allow-writes]] [--export-dir DIR]
                  [--smpl-model PATH] [--frame N] [--track K]
                  [--rerun [--rerun-port 9090] [--rerun-save RRD]]
    python app.py --batch DIR     (the scenes of a mvviz batch report)

Loads SCENE (default sample_data/shelf_synth), runs the pipeline or reuses its cached
results (SCENE/.mvviz/results.npz), and serves the viewer at http://127.0.0.1:8080.
Scrub the timeline, toggle layers (cameras with their video, 2D detections on the image
planes, rays, raw / filtered / ground-truth skeletons, trails, ground-truth and fitted
SMPL meshes), click a joint to select it; re-run the per-frame stages with other
parameters or cameras off (Pipeline), tune a second Kalman filter side by side
(Filter A/B), jump to the worst moments (Failures). Same as ``mvviz view SCENE``.
With --batch DIR, the scenes of DIR/batch_report.json (``mvviz batch``) in a Dataset
tab, sorted by a metric, worst first: a click opens a scene at its worst moment.
With --rerun, rerun's web viewer (from the rerun-sdk package) is served too, on
--rerun-port, and logged into live (mvviz/export/rerun_live.py).
Binds to 127.0.0.1 unless --host says otherwise; the viewer has no authentication, so on
any other address it warns and is read-only (no export, no save) unless --allow-writes.
Files a page asks for go into --export-dir (default SCENE/.mvviz/export) or the scene
folder, never elsewhere. Ctrl-C stops the server.
"""

from __future__ import annotations

import argparse
import sys

from mvviz.cli import add_debug_option, run_command
from mvviz.cli.view import add_view_options, run


def build_parser() -> argparse.ArgumentParser:
    """The viewer's options (also the documentation's command reference)."""
    parser = argparse.ArgumentParser(
        prog="python app.py",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_view_options(parser, scene_optional=True)
    add_debug_option(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.batch is not None:
        # the report's modules (matplotlib) load only with --batch: the start stays fast
        from mvviz.cli.view_batch import run_batch

        return run_command("app.py", run_batch, args)
    return run_command("app.py", run, args)


if __name__ == "__main__":
    sys.exit(main())
