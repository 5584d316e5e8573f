"""Held-out protocol for the SMPL fit and its VAE correction: train the prior without some
motion, score on a scene synthesised from exactly that motion.

Splits (``--split``, default all; sources and activities of
:mod:`pipeline.prior.sources`):

* leave one source out: ``no-library`` (prior: CMU + balancing + demo; test: library
  motion of every activity, 4 people), ``no-cmu`` (prior: library + balancing + demo; test:
  CMU 131_01 walking and 131_03 hopping), ``no-balancing`` (prior: library + CMU + demo;
  test: the balancing trial's poses; it is also the leave-one-activity-out split of
  ``balance``); the demo (the Pose2Sim demo's two people, standing and walking) is a
  training source only;
* leave one activity out, in every source at once: ``no-walk`` (test: CMU walking
  131_01/131_02; the demo, which shows walking, left out whole), ``no-hop`` (test:
  131_03), ``no-reach``, ``no-crouch``, ``no-wave`` (test: library motion of that
  activity, two variants).

Each test scene: :func:`pipeline.synth.mocap_scene.write_mocap_scene` on the campus rig,
``--frames`` frames at 25 fps, default detector noise, seed 0 (BVH clips as
``mvviz synth --motion``; library motion and the balancing poses through
:func:`pipeline.mocap.clips.clip_from_body`, whose truth is our body model: all 24 SMPL joints
scored; library walking with the measured ankle gait curve, see :func:`library_clip`).
Each prior: :func:`pipeline.prior.sources.train_on`, the shipped prior's recipe with
fewer poses and epochs (``--num-poses 20000 --epochs 30``: a split takes
minutes, not ten, on 2 shared cores; ``--num-poses 60000 --epochs 60`` is the shipped
recipe). Before scoring, :func:`pipeline.prior.heldout.check_disjoint` proves the prior never saw
a frame the scene plays, and for an activity split
:func:`pipeline.prior.heldout.check_activity_held_out` that no source showed the activity.
Reported per phase (raw, RTS, step I, SMPL + VAE): MPJPE on the measured COCO joints
(the 12 body joints for a BVH clip, 17 keypoints for a body-model clip), MPJPE on the SMPL
joints of the truth (16 mapped for a CMU skeleton, 24 otherwise), joint-limit and hinge
violations per 1,000 bodies, foot and wrist jitter (mm/frame^2).

Usage:
    python bench/bench_prior_heldout.py [--split NAME ...] [--work DIR] [--frames F]
        [--epochs E] [--num-poses N] [--json FILE] [--markdown]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import write_json  # noqa: E402
from pipeline.body.model import BodyModel, load_body_model  # noqa: E402
from pipeline.config import PipelineConfig  # noqa: E402
from pipeline.data.scene import load_scene  # noqa: E402
from pipeline.evaluation.evaluate import evaluate  # noqa: E402
from pipeline.fit.prior import load_prior, save_prior  # noqa: E402
from pipeline.importers.calibration import read_voxelpose_calibration  # noqa: E402
from pipeline.mocap.clips import MocapClip, clip_from_body, load_mocap_clip  # noqa: E402
from pipeline.prior.heldout import check_activity_held_out, check_disjoint  # noqa: E402
from pipeline.prior.sources import BALANCING_POSES, CMU_DIR, sources_for, train_on  # noqa: E402
from pipeline.run.pipeline import run_or_load  # noqa: E402
from pipeline.synth.mocap_scene import MocapSceneConfig, write_mocap_scene  # noqa: E402
from pipeline.synth.motion import PersonMotion, activity_params, walk_params  # noqa: E402
from pipeline.synth.scene_gen import bodies_from_motion  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
RIG = REPO / "sample_data" / "rigs" / "campus_voxelpose.json"
PHASES = ("raw", "rts", "smpl", "smpl_vae")


@dataclass(frozen=True)
class Split:
    """A prior trained without ``exclude_sources`` / ``exclude_activities``, tested on
    ``test`` clips (``cmu:131_01.bvh``, ``library:reach:0``, ``balancing``)."""

    exclude_sources: tuple[str, ...]
    exclude_activities: tuple[str, ...]
    test: tuple[str, ...]
    people: int = 2


SPLITS: dict[str, Split] = {
    "no-library": Split(
        ("library",),
        (),
        ("library:walk:0", "library:reach:0", "library:crouch:0", "library:wave:0"),
        people=4,
    ),
    "no-cmu": Split(("cmu",), (), ("cmu:131_01.bvh", "cmu:131_03.bvh")),
    "no-balancing": Split(("balancing",), ("balance",), ("balancing",), people=1),
    "no-walk": Split((), ("walk",), ("cmu:131_01.bvh", "cmu:131_02.bvh")),
    "no-hop": Split((), ("hop",), ("cmu:131_03.bvh",)),
    "no-reach": Split((), ("reach",), ("library:reach:0", "library:reach:1")),
    "no-crouch": Split((), ("crouch",), ("library:crouch:0", "library:crouch:1")),
    "no-wave": Split((), ("wave",), ("library:wave:0", "library:wave:1")),
}


def library_clip(kind: str, variant: int, model: BodyModel, *, fps: float = 25.0,
                 seconds: float = 3.0) -> MocapClip:  # fmt: skip
    """``seconds`` of one library activity played by a random body (seeded by ``variant``);
    walking goes straight ahead at 1.2 m/s, its ankles on the measured gait curve
    (``walk_params(gait_ankles=True)``; the default +-8.6 deg sine dorsiflexes at toe off,
    where people plantarflex 20 deg). The shipped samples and the training library keep
    the sine."""
    rng = np.random.default_rng(1000 + variant)
    n = int(round(seconds * fps))
    t = np.arange(n) / fps
    heading = np.zeros(n)
    position = np.zeros((n, 2))
    if kind == "walk":
        speed = np.full(n, 1.2)
        params = walk_params(rng.uniform() + t * 1.2 / 1.35, speed, gait_ankles=True)
        position[:, 1] = 1000.0 * speed * t  # heading 0 faces world +y
    else:
        params = activity_params(kind, t, rng.uniform(size=8))
    betas = np.clip(rng.normal(0, 1, 10), -2.5, 2.5)
    motion = PersonMotion(params, heading, position, betas, np.full(n, kind, dtype=object))
    people = bodies_from_motion([motion], model)
    return clip_from_body(
        f"library_{kind}_{variant}", people.pose[0], betas, people.transl[0], model,
        fps=fps, activity=kind, licence="generated",
    )  # fmt: skip


def balancing_clip(model: BodyModel, *, fps: float = 25.0) -> MocapClip:
    """The balancing trial's fitted poses (60 fps), resampled to ``fps`` by nearest frame."""
    with np.load(BALANCING_POSES, allow_pickle=False) as z:
        poses, trans, betas = z["poses"], z["trans"], z["betas"]
        src_fps = float(z["mocap_framerate"])
    idx = np.round(np.arange(0, len(poses) - 1e-9, src_fps / fps)).astype(int)
    idx = idx[idx < len(poses)]
    return clip_from_body(
        BALANCING_POSES.name, poses[idx].reshape(-1, 24, 3), betas, 1000.0 * trans[idx], model,
        fps=fps, activity="balance", licence="BSD-3-Clause", source_frames=len(poses),
        source_fps=src_fps,
    )  # fmt: skip


def make_clips(test: tuple[str, ...], model: BodyModel) -> list[MocapClip]:
    out = []
    for spec in test:
        kind, _, rest = spec.partition(":")
        if kind == "cmu":
            out.append(load_mocap_clip(CMU_DIR / rest, fps=25.0))
        elif kind == "library":
            act, _, variant = rest.partition(":")
            out.append(library_clip(act, int(variant), model))
        elif kind == "balancing":
            out.append(balancing_clip(model))
        else:
            raise ValueError(f"unknown test clip {spec!r}")
    return out


def make_scene(split: Split, out: Path, frames: int, model: BodyModel) -> Path:
    if not (out / "scene.json").is_file():
        clips = make_clips(split.test, model)
        config = MocapSceneConfig(motions=(), num_people=split.people, num_frames=frames, seed=0)
        rig = read_voxelpose_calibration(RIG)
        write_mocap_scene(out, rig, model, config, clips=clips, overwrite=True, progress=False)
    return out


def make_prior(split: Split, out: Path, *, epochs: int, num_poses: int) -> Path:
    if not out.is_file():
        sources = sources_for(
            exclude_sources=split.exclude_sources,
            exclude_activities=split.exclude_activities,
            num_poses=num_poses,
        )
        save_prior(train_on(sources, epochs=epochs, progress=False), out)
    return out


def score(scene_dir: Path, prior_path: Path, split: Split, model) -> dict[str, dict[str, float]]:
    scene = load_scene(scene_dir)
    prior = load_prior(prior_path)
    sources = prior.info.get("sources", [])
    check_disjoint(sources, scene.meta["synth"])
    for activity in split.exclude_activities:
        check_activity_held_out(sources, activity)
    for s in sources:
        if s.get("source") in split.exclude_sources:
            raise ValueError(f"the prior was trained on the held-out source {s['source']}")
    config = PipelineConfig(pose_prior=str(prior_path))
    results, _ = run_or_load(scene, config, model, progress=False)
    ev = evaluate(scene, results)
    out = {}
    for phase in PHASES:
        st, pl = ev.stages[phase], ev.plausibility[phase]
        out[phase] = {
            "mpjpe_measured_mm": st["mpjpe"],
            "mpjpe_smpl_joints_mm": ev.smpl24.get(phase, {}).get("mpjpe", float("nan")),
            "limit_violations_per_1000": pl.get("limit_violations_per_1000", float("nan")),
            "hinge_violations_per_1000": pl["hinge_violations_per_1000"],
            "foot_jitter": pl["foot_jitter"],
            "wrist_jitter": pl["wrist_jitter"],
        }
    return out


COLUMNS = (
    ("mpjpe_measured_mm", "MPJPE measured"),
    ("mpjpe_smpl_joints_mm", "MPJPE SMPL joints"),
    ("limit_violations_per_1000", "limits /1k"),
    ("hinge_violations_per_1000", "hinge /1k"),
    ("foot_jitter", "foot jit"),
    ("wrist_jitter", "wrist jit"),
)
NAMES = {"raw": "raw", "rts": "RTS", "smpl": "step I", "smpl_vae": "SMPL + VAE"}


def _cell(x: float) -> str:
    return "-" if not np.isfinite(x) else f"{x:.1f}"


def markdown(table: dict) -> str:
    head = "| split | phase | " + " | ".join(c for _, c in COLUMNS) + " |"
    lines = [head, "|" + "---|" * (len(COLUMNS) + 2)]
    for name, rows in table.items():
        for phase, v in rows.items():
            if phase.startswith("_"):
                continue
            lines.append(
                f"| {name} | {NAMES[phase]} | " + " | ".join(_cell(v[k]) for k, _ in COLUMNS) + " |"
            )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--split", nargs="+", choices=list(SPLITS), default=list(SPLITS))
    parser.add_argument("--work", type=Path, default=Path("/tmp/mvviz_prior_heldout"))
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--epochs", type=int, default=30,
                        help="epochs of each held-out prior (shipped prior: 60)")  # fmt: skip
    parser.add_argument("--num-poses", type=int, default=20000,
                        help="library poses before filtering (shipped prior: 60000)")  # fmt: skip
    parser.add_argument("--json", type=Path)
    parser.add_argument("--markdown", action="store_true", help="print one markdown table")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    model = load_body_model()
    table = {}
    for name in args.split:
        split = SPLITS[name]
        tag = name.removeprefix("no-")
        t0 = time.perf_counter()
        ckpt = args.work / f"prior_without_{tag}_e{args.epochs}_n{args.num_poses}.pt"
        prior = make_prior(split, ckpt, epochs=args.epochs, num_poses=args.num_poses)
        t1 = time.perf_counter()
        # "_gait": scenes cached before the library walk took the gait ankles are not reused.
        scene_dir = args.work / f"scene_{tag}_{args.frames}_gait"
        scene = make_scene(split, scene_dir, args.frames, model)
        table[name] = score(scene, prior, split, model)
        t2 = time.perf_counter()
        print(f"\n{name}: prior without sources {list(split.exclude_sources)} and activities "
              f"{list(split.exclude_activities)}; test {list(split.test)} "
              f"(prior {t1 - t0:.0f} s, scene + fit {t2 - t1:.0f} s)", flush=True)  # fmt: skip
        print(f"{'phase':11s}" + "".join(f"{c:>18s}" for _, c in COLUMNS))
        for phase, v in table[name].items():
            print(f"{NAMES[phase]:11s}" + "".join(f"{_cell(v[k]):>18s}" for k, _ in COLUMNS))
    if args.markdown:
        print("\n" + markdown(table))
    if args.json:
        write_json(args.json, table)


if __name__ == "__main__":
    main()
