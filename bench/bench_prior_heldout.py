"""Held-out protocol for the SMPL fit and its VAE correction: train the prior on some
sources, score on scenes synthesised from motion it has not seen.

Splits (``--split``, default all): ``library->cmu`` (prior: the synthetic library only,
the former shipped prior; test: every CMU 131 clip), ``walks->hop`` (prior: library +
131_01 + 131_02; test: the hop 131_03), ``hop+walk->walk`` (prior: library + 131_01 +
131_03; test: 131_02). Each test scene is ``mvviz synth OUT --motion CLIP... --rig
campus --people 2 --frames 40 --seed 0`` (default detector noise); each prior
``mvviz train-prior --data CLIP.bvh ... --with-library``. Before scoring,
:func:`pipeline.heldout.check_disjoint` proves the prior never saw a frame the scene
plays. Reported per phase (raw, RTS, step I, SMPL + VAE): MPJPE on the 12 measured
COCO joints (vs ``keypoints3d`` where raw has the joint), MPJPE on the 16 mapped SMPL
joints, joint-limit and hinge violations per 1,000 bodies, foot and wrist jitter
(mm/frame^2).

Usage:
    python bench/bench_prior_heldout.py [--split NAME ...] [--work DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import write_json  # noqa: E402
from pipeline.body_model import load_body_model  # noqa: E402
from pipeline.config import PipelineConfig  # noqa: E402
from pipeline.evaluate import evaluate  # noqa: E402
from pipeline.heldout import check_disjoint  # noqa: E402
from pipeline.pose_prior import load_prior  # noqa: E402
from pipeline.results import run_or_load  # noqa: E402
from pipeline.scene import load_scene  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CMU = REPO / "sample_data" / "mocap" / "cmu131"
SPLITS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    # name: (BVH clips the prior adds to the library, BVH clips of the test scene)
    "library->cmu": ((), ("131_01", "131_02", "131_03")),
    "walks->hop": (("131_01", "131_02"), ("131_03",)),
    "hop+walk->walk": (("131_01", "131_03"), ("131_02",)),
}
PHASES = ("raw", "rts", "smpl", "smpl_vae")


def _run(cmd: list[str]) -> None:
    subprocess.run(cmd, check=True, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def make_prior(train: tuple[str, ...], out: Path) -> Path:
    if not train:
        return out  # caller passes the library-only checkpoint
    if not out.is_file():
        data = [str(CMU / f"{c}.bvh") for c in train]
        _run(["mvviz", "train-prior", "--data", *data, "--with-library", "--out", str(out)])
    return out


def make_scene(test: tuple[str, ...], out: Path, frames: int) -> Path:
    if not (out / "scene.json").is_file():
        motions = [a for c in test for a in ("--motion", str(CMU / f"{c}.bvh"))]
        _run(["mvviz", "synth", str(out), *motions, "--rig", "campus", "--people", "2",
              "--frames", str(frames), "--seed", "0", "--overwrite"])  # fmt: skip
    return out


def score(scene_dir: Path, prior_path: Path, model) -> dict[str, dict[str, float]]:
    scene = load_scene(scene_dir)
    prior = load_prior(prior_path)
    check_disjoint(prior.info.get("sources", []), scene.meta["synth"])
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


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--split", nargs="+", choices=list(SPLITS), default=list(SPLITS))
    parser.add_argument("--work", type=Path, default=Path("/tmp/mvviz_prior_heldout"))
    parser.add_argument("--library-prior", type=Path, default=None,
                        help="library-only checkpoint (default: trained into --work)")  # fmt: skip
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    model = load_body_model()
    lib = args.library_prior or args.work / "prior_library.pt"
    if not lib.is_file():
        _run(["mvviz", "train-prior", "--out", str(lib)])
    table = {}
    for name in args.split:
        train, test = SPLITS[name]
        tag = name.replace("->", "_to_").replace("+", "_")
        prior = make_prior(train, args.work / f"prior_{tag}.pt") if train else lib
        scene = make_scene(test, args.work / f"scene_{tag}", args.frames)
        table[name] = score(scene, prior, model)
        print(f"\n{name}: prior = library + {list(train)}, test = {list(test)}")
        print(f"{'phase':9s} {'MPJPE12':>8s} {'MPJPE16':>8s} {'limits/1k':>9s} {'hinge/1k':>8s} "
              f"{'foot jit':>8s} {'wrist jit':>9s}")  # fmt: skip
        for phase, v in table[name].items():
            print(
                f"{phase:9s} {v['mpjpe_measured_mm']:8.1f} {v['mpjpe_smpl_joints_mm']:8.1f} "
                f"{v['limit_violations_per_1000']:9.1f} {v['hinge_violations_per_1000']:8.1f} "
                f"{v['foot_jitter']:8.1f} {v['wrist_jitter']:9.1f}"
            )
    if args.json:
        write_json(args.json, table)


if __name__ == "__main__":
    main()
