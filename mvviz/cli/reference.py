"""``mvviz add-reference``: attach another tool's 3D result to an existing scene.

Example (Pose2Sim's triangulation of the same trial, drawn beside ours by the viewer):

    mvviz add-reference scenes/balancing pose2sim ref3d/trial_0-100.trc

The TRC's markers (Pose2Sim's names) are mapped onto the scene's joint set, metres and
OpenSim's Y-up axes onto world millimetres, z up; TRC row i is scene frame i (a shorter
TRC is padded with missing frames, a longer one refused). Written into
``SCENE/references/NAME.npz`` and ``scene.json``, each atomically.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

from pipeline.data.scene import add_reference, load_scene
from pipeline.importers.trc import reference_from_trc


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``add-reference`` subcommand to ``sub``."""
    p = sub.add_parser(
        "add-reference",
        help="attach another tool's 3D result (a Pose2Sim TRC) to a scene as a reference",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("scene", type=Path, help="scene directory")
    p.add_argument("name", help="reference name (letters, digits, _ . -), e.g. pose2sim")
    p.add_argument("trc", type=Path, metavar="FILE.trc", help="TRC file (Pose2Sim / OpenSim)")
    p.add_argument(
        "--z-up", action="store_true", help="the TRC is already z up (default: Y up, OpenSim's)"
    )
    p.add_argument("--overwrite", action="store_true", help="replace a reference of that name")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Attach; format errors propagate to ``mvviz.cli.main`` (exit code 2)."""
    scene = load_scene(args.scene)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            track = reference_from_trc(
                args.trc, args.name, scene.joint_set, fps=scene.fps, y_up=not args.z_up
            )
            path = add_reference(scene, track, overwrite=args.overwrite)
        finally:
            for w in caught:
                print(f"mvviz add-reference: warning: {w.message}", file=sys.stderr)
    scene = load_scene(args.scene)  # read back: what the viewer will see
    j = scene.references[args.name].joints
    frames = int(np.isfinite(j).all(-1).any(-1).sum())
    joints = int(np.isfinite(j).all(-1).any(0).sum())
    print(
        f"wrote {path}: {joints} of {scene.joint_set.num_joints} {scene.joint_set.name} "
        f"joints in {frames} of {scene.num_frames} frames"
    )
    return 0
