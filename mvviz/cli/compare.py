"""mvviz compare: two complete configurations of one scene, run over the whole sequence
and compared side by side (pipeline/diagnose/compare_runs.py).

Each side is a config file (``--a CFG`` / ``--b CFG``; default: the scene's saved
mvviz_config.json, else the defaults) with ``--a-set`` / ``--b-set`` overrides (any field
of any stage, as ``mvviz run --set``); ``--set`` applies to both. A configuration run
before is read from the scene's cache, not recomputed.

Printed: the fields that differ, the figures of each run (association, tracks, ID
switches, MPJPE / PCK / PCP / acceleration error per stage where there is ground truth,
reprojection per camera, the SMPL fits' residual), and the frames and people where the
runs differ most (3D distance between A's and B's joints of the same person, spans
merged), each with the command that opens the viewer there.

Examples:

    mvviz compare SCENE --b-set kalman.q=10000
    mvviz compare SCENE --a old.json --b new.json --top 5 --json ab.json
    mvviz compare SCENE --b-set disabled_views=cam02 --set fit_smpl=false
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from pipeline.body.model import load_body_model
from pipeline.config import CONFIG_FILE, PipelineConfig, load_config
from pipeline.core.files import SceneFormatError, atomic_write
from pipeline.data.scene import load_scene
from pipeline.diagnose.compare_runs import (
    MATCH_GATE_MM,
    MIN_DIFF_MM,
    compare_runs,
    run_cached,
    view_command,
)
from pipeline.fit.prior import load_prior


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "compare",
        help="run two configurations over the whole sequence and compare them (A/B)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("scene", type=Path, help="scene directory (see sample_data/README.md)")
    for side in ("a", "b"):
        p.add_argument(
            f"--{side}", type=Path, default=None, metavar="CFG",
            help=f"config file of run {side.upper()} (default: the scene's {CONFIG_FILE})",
        )  # fmt: skip
        p.add_argument(
            f"--{side}-set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
            help=f"override a value of run {side.upper()} (repeatable)",
        )  # fmt: skip
    p.add_argument(
        "--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
        help="override a value of both runs, e.g. --set fit_smpl=false (repeatable)",
    )  # fmt: skip
    p.add_argument("--top", type=int, default=10, help="differences listed (default 10)")
    p.add_argument(
        "--min-mm", type=float, default=MIN_DIFF_MM,
        help=f"a person's joints this far apart differ (default {MIN_DIFF_MM:g} mm)",
    )  # fmt: skip
    p.add_argument("--json", type=Path, default=None, metavar="FILE", help="also write JSON")
    p.add_argument("--smpl-model", default=None, help="body model file (.npz/.pkl)")
    p.add_argument("--force", action="store_true", help="re-run both, ignore the cache")
    p.set_defaults(func=run)


def side_config(args: argparse.Namespace, side: str) -> tuple[PipelineConfig, list[str]]:
    """Run ``side``'s config and the ``mvviz view`` options that give it."""
    path = getattr(args, side)
    overrides = [*args.set, *getattr(args, f"{side}_set")]
    where = f"--{side}"
    view_args: list[str] = []
    if path is not None:
        view_args += ["--config", str(path)]
    elif (args.scene / CONFIG_FILE).is_file():
        path = args.scene / CONFIG_FILE  # what `mvviz view SCENE` reads too
    config = load_config(path) if path else PipelineConfig()
    try:
        config = config.with_overrides(overrides)
    except SceneFormatError as exc:
        raise SceneFormatError(f"{where}-set", None, str(exc)) from None
    for o in overrides:
        view_args += ["--set", o]
    return config, view_args


def run(args: argparse.Namespace) -> int:
    if args.top < 1:
        raise SceneFormatError("--top", None, f"expected >= 1, got {args.top}")
    if not (math.isfinite(args.min_mm) and args.min_mm > 0):
        raise SceneFormatError("--min-mm", None, f"expected a number > 0, got {args.min_mm}")
    scene = load_scene(args.scene)
    (cfg_a, view_a), (cfg_b, _) = side_config(args, "a"), side_config(args, "b")
    for side, cfg in (("a", cfg_a), ("b", cfg_b)):
        cfg.check_cameras(scene.rig.names, source=f"--{side}")
        if cfg.fit_smpl and cfg.use_pose_prior:
            load_prior(cfg.pose_prior or None)
    model = load_body_model(args.smpl_model)
    runs = {}
    for side, cfg in (("A", cfg_a), ("B", cfg_b)):
        res, reused, path = run_cached(scene, cfg, model, force=args.force)
        print(f"run {side}: {'reused cached' if reused else 'computed'} {path}")
        runs[side] = res
    cmp = compare_runs(scene, runs["A"], runs["B"], min_mm=args.min_mm)
    for line in report_lines(cmp, scene_root=args.scene, view_args=view_a, top=args.top):
        print(line)
    if args.json is not None:
        with atomic_write(args.json, "w") as fh:
            json.dump(cmp.to_json(top=args.top), fh, indent=1, default=str)
        print(f"wrote {args.json}")
    return 0


def _num(x: float) -> str:
    if not math.isfinite(x):
        return "-"
    return f"{x:.0f}" if float(x).is_integer() and abs(x) >= 1 else f"{x:.3g}" if abs(x) < 1 \
        else f"{x:.1f}"  # fmt: skip


def describe(d) -> str:
    """One difference in words (the CLI's and the viewer's)."""
    if d.kind != "moved":
        return f"{d.kind} (the other run has no one within {MATCH_GATE_MM:.0f} mm)"
    text = f"{d.peak_mm:.0f} mm apart at frame {d.peak_frame} (mean {d.mean_mm:.0f})"
    coast = [f"{n} of {d.frames} frames unmeasured in {s}"
             for s, n in (("A", d.unmeasured_a), ("B", d.unmeasured_b)) if n]  # fmt: skip
    return text + (f"; {', '.join(coast)} (the filter coasts)" if coast else "")


def report_lines(cmp, *, scene_root, view_args: list[str], top: int) -> list[str]:
    """What ``mvviz compare`` prints (also the viewer's table, as text)."""
    out = ["fields that differ (A -> B):"]
    out += [f"  {k}: {a!r} -> {b!r}" for k, a, b in cmp.config_changes] or ["  none"]
    width = max((len(n) for n, _, _ in cmp.rows), default=10)
    out.append(f"{'figure':<{width}}  {'A':>9}  {'B':>9}  {'B - A':>9}")
    for name, a, b in cmp.rows:
        out.append(f"{name:<{width}}  {_num(a):>9}  {_num(b):>9}  {_num(b - a):>9}")
    shown = cmp.top(top)
    out.append(f"where they differ most ({len(cmp.differences)} spans; {len(shown)} shown):")
    for d in shown:
        who = f"track {d.track_a} (A) / {d.track_b} (B)"
        what = describe(d)
        out.append(f"  frames {d.start}-{d.stop}: {who}: {what}")
        out.append(f"    {view_command(scene_root, d, config_args=view_args)}")
    if not shown:
        out.append("  none: every person within the threshold in every frame")
    return out
