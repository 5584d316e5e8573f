"""``mvviz run`` and ``mvviz eval``: the pipeline on a scene, and its scores."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from pipeline.body.arrays import BodyModelData, load_body_model_data
from pipeline.config import CONFIG_FILE, PipelineConfig, load_config
from pipeline.core.files import SceneFormatError, atomic_write
from pipeline.data.joint_sets import get_joint_set
from pipeline.data.scene import Scene, load_scene
from pipeline.diagnose.sync import estimate_offsets
from pipeline.evaluation.evaluate import evaluate, format_table, stage_tracks
from pipeline.evaluation.protocol import (
    PROTOCOL_TRUTH_FILE,
    PROTOCOLS,
    estimates_by_frame,
    format_protocol_table,
    load_scene_protocol,
    read_protocol_gt,
    score_protocol,
)
from pipeline.fit.prior_path import resolve_prior_path
from pipeline.results.store import default_results_path
from pipeline.run.pipeline import run_or_load
from pipeline.stages.retime import offsets_setting


def add_config_options(p: argparse.ArgumentParser) -> None:
    """``--config``, ``--set`` and ``--smpl-model``: what :func:`prepare` reads."""
    p.add_argument("--config", type=Path, default=None, help="pipeline config JSON")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.FIELD=VALUE",
        help="override a config value, e.g. --set kalman.q=50 --set source=smpl (repeatable)",
    )
    p.add_argument("--smpl-model", default=None, help="body model file (.npz/.pkl)")


def add_pipeline_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", type=Path, help="scene directory (see sample_data/README.md)")
    add_config_options(p)
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="results file (default SCENE/.mvviz/results.npz); a path not ending in .npz is "
        "a directory of memory-mapped arrays the viewer reads frame by frame (long scenes)",
    )
    p.add_argument("--force", action="store_true", help="ignore cached results")


def resolve_config(args: argparse.Namespace) -> PipelineConfig:
    """The run's config: --config FILE, else SCENE/mvviz_config.json if present, then --set."""
    path = args.config
    if path is None and (args.scene / CONFIG_FILE).is_file():
        path = args.scene / CONFIG_FILE
    config = load_config(path) if path else PipelineConfig()
    return config.with_overrides(args.set)


def prepare(
    args: argparse.Namespace, *, read_prior: bool = True
) -> tuple[Scene, PipelineConfig, BodyModelData]:
    """Scene, config and body model, every input checked before any stage runs (the
    config against the scene's cameras, the pose prior checkpoint if the fit uses it).

    ``read_prior`` False (the viewer, which mostly loads cached results): the checkpoint
    is only checked to exist; reading it needs torch, which loads once a fit runs."""
    scene = load_scene(args.scene)
    config = resolve_config(args)
    config.check_cameras(scene.rig.names, source=str(args.config or "--set"))
    model = load_body_model_data(args.smpl_model)
    if config.fit_smpl and config.use_pose_prior:
        if read_prior:
            from pipeline.fit.prior import load_prior  # torch

            load_prior(config.pose_prior or None)
        elif not resolve_prior_path(config.pose_prior or None).is_file():
            path = resolve_prior_path(config.pose_prior or None)
            raise SceneFormatError(path, None, "pose prior checkpoint not found")
    return scene, config, model


def cached_results(args: argparse.Namespace):
    """(scene, results, model) of :func:`prepare`'s inputs, reusing the cached run (the
    exports' way in); says whether the results were reused."""
    scene, config, model = prepare(args)
    results, cached = run_or_load(scene, config, model)
    print(f"{'reused cached' if cached else 'computed'} results: {results.num_tracks} tracks")
    from pipeline.body.model import torch_body_model  # the exports skin

    return scene, results, torch_body_model(model)


def load_and_run(args: argparse.Namespace, *, progress: bool = True):
    scene, config, model = prepare(args)
    t0 = time.perf_counter()
    results, cached = run_or_load(
        scene, config, model, out=args.out, progress=progress, force=args.force
    )
    took = time.perf_counter() - t0
    return scene, results, cached, took


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="run the pipeline on a scene and write its results file",
        description=(
            "Restoration, association, triangulation, tracking and Kalman filtering on every "
            "frame of SCENE; writes one results file (atomically). A re-run with the same scene "
            "and config reuses it."
        ),
    )
    add_pipeline_options(p)
    p.set_defaults(func=run)

    e = sub.add_parser(
        "eval",
        help="score a run against the scene's ground truth",
        description=(
            "Prints MPJPE, PCK@160 mm, PCP and acceleration error per stage (raw triangulation, "
            "+ Kalman, + RTS), association precision/recall and ID switches, and per-view "
            "reprojection errors. Runs the pipeline first if needed."
        ),
    )
    add_pipeline_options(e)
    e.add_argument("--json", type=Path, default=None, help="also write the figures as JSON")
    e.add_argument(
        "--sync", action=argparse.BooleanOptionalAction, default=None,
        help="check the cameras' time offsets (pipeline/diagnose/sync.py); default: when the "
        f"scene has at most {SYNC_AUTO_LIMIT} frames x cameras (~1.2 ms each)",
    )  # fmt: skip
    e.add_argument(
        "--no-other-source",
        action="store_true",
        help="do not also score the other 2D source (keypoints / restored SMPL)",
    )
    e.add_argument(
        "--protocol", choices=PROTOCOLS, default=None,
        help="score by the Shelf / Campus protocol (PCP of its 14 joints per actor, limb and "
        "stage; pipeline/evaluation/protocol.py) against --gt",
    )  # fmt: skip
    e.add_argument(
        "--gt", type=Path, default=None,
        help="the protocol's truth: the datasets' actorsGT.mat, or an .npz of frame, "
        "person_id, joints3d (N, 14 or 15, 3) mm (default: the one the scene stores)",
    )  # fmt: skip
    e.set_defaults(func=run_eval)


SYNC_AUTO_LIMIT = 20_000


def _protocol_eval(args, scene: Scene, results, truth) -> int:
    """``mvviz eval --protocol``: the protocol's table of every stage, and its JSON."""
    joint_set = get_joint_set(results.joint_set)
    scores = {
        name: score_protocol(estimates_by_frame(tracks, joint_set), truth)
        for name, tracks in stage_tracks(results).items()
    }
    print(f"scene {scene.name}: {args.protocol} protocol against {truth.source}")
    print(format_protocol_table(scores))
    present = np.isfinite(results.track_raw).all(-1).any(-1)  # (K, F)
    lengths = present.sum(1)
    long_tracks = int((lengths >= 20).sum())
    print(f"tracks: {results.num_tracks}, of them {long_tracks} of 20 frames or more")
    if args.json:
        report = {
            "protocol": args.protocol,
            "gt": truth.source,
            "stages": {name: s.as_dict() for name, s in scores.items()},
            "tracks": {"count": int(results.num_tracks), "long": long_tracks},
        }
        with atomic_write(args.json, "w") as fh:
            json.dump(report, fh, indent=1, default=float)
    return 0
"""Frames x cameras up to which ``mvviz eval`` checks sync unasked: measured 1.5 s for
250 x 5 (shelf_synth, 1.2 ms per frame and camera, on 2 busy cores) beside ~20 s for the
rest of a cached eval; 20,000 is ~25 s, a 10-minute 8-camera capture would be ~3 min."""


def sync_report(scene: Scene, results, wanted: bool | None) -> dict | None:
    """Print the ``sync:`` line (per camera its offset and confidence) and return it as
    JSON; None when not checked (``wanted`` False, or None and the scene is large)."""
    size = scene.num_frames * len(scene.rig)
    if wanted is False or (wanted is None and size > SYNC_AUTO_LIMIT):
        if wanted is None:
            print(f"sync: not checked ({scene.num_frames} frames x {len(scene.rig)} cameras; "
                  f"--sync checks it, ~{size * 1.2e-3:.0f} s)")  # fmt: skip
        return None
    t0 = time.perf_counter()
    est = estimate_offsets(scene, results)
    parts = []
    for name, e in est.items():
        flag = " LATE" if e.offset and e.offset_frames > 0 else " EARLY" if e.offset else ""
        parts.append(f"{name} {e.offset_frames:+.2f} ({e.confidence:.2f}){flag}")
    late = {k: e.offset_frames for k, e in est.items() if e.offset}
    hint = ""
    if late:
        hint = (
            f"; apply: --set sync.offsets={offsets_setting(late, results.config.sync.by_camera())}"
        )
    print(f"sync: offset frames (confidence) {', '.join(parts)}{hint}"
          f"  [{time.perf_counter() - t0:.1f} s]")  # fmt: skip
    return {k: {"offset_frames": round(e.offset_frames, 3), "confidence": round(e.confidence, 3)}
            for k, e in est.items()}  # fmt: skip


def run(args: argparse.Namespace) -> int:
    scene, results, cached, took = load_and_run(args)
    path = args.out or default_results_path(scene)
    how = "reused cached" if cached else "computed"
    print(
        f"{how} results for {scene.name}: {results.num_frames} frames, "
        f"{len(results.person_frame)} person-frames, {results.num_tracks} tracks "
        f"({took:.1f} s) -> {path}"
    )
    return 0


def run_eval(args: argparse.Namespace) -> int:
    if args.gt is not None and args.protocol is None:
        raise SceneFormatError(args.gt, None, "--gt is the protocol's truth: give --protocol too")
    truth = read_protocol_gt(args.gt) if args.gt is not None else None
    if args.protocol is not None and truth is None:
        stored = load_scene_protocol(args.scene)
        if stored is None:
            raise SceneFormatError(
                Path(args.scene) / PROTOCOL_TRUTH_FILE, None,
                "no protocol truth in the scene: give --gt (or store it with mvviz convert "
                "--protocol-gt)",
            )  # fmt: skip
        truth = stored[1]
    scene, results, _, _ = load_and_run(args)
    if truth is not None:
        return _protocol_eval(args, scene, results, truth)
    ev = evaluate(scene, results)
    print(f"scene {scene.name}: source={results.config.source}, joint set {results.joint_set}")
    print(format_table(ev, view_names=scene.rig.names))
    report = ev.to_json()
    report["source"] = results.config.source
    if scene.detections.has_mono3d and not args.no_other_source:
        # Rows carry both 2D keypoints and monocular SMPL output: score the other source too.
        other = "smpl" if results.config.source == "keypoints" else "keypoints"
        model = load_body_model_data(args.smpl_model)
        alt_cfg = dataclasses.replace(results.config, source=other)
        alt_out = (
            (args.out.with_name(args.out.stem + f"_{other}.npz"))
            if args.out
            else (default_results_path(scene).with_name(f"results_{other}.npz"))
        )
        alt, _ = run_or_load(scene, alt_cfg, model, out=alt_out, progress=False, force=args.force)
        alt_ev = evaluate(scene, alt)
        print(f"\nthe other source: source={other}, joint set {alt.joint_set}")
        print(format_table(alt_ev, view_names=scene.rig.names))
        report["other_source"] = dict(alt_ev.to_json(), source=other)
    sync = sync_report(scene, results, args.sync)
    if sync is not None:
        report["sync"] = sync
    if scene.gt is None:
        print("(no gt.npz: pose rows need ground truth)", file=sys.stderr)
    if args.json:
        with atomic_write(args.json, "w") as fh:
            json.dump(report, fh, indent=1, default=float)
    return 0
