"""Bodies of real proportions: the fit against the floor of constant bone lengths.

For each case the pipeline runs twice in the same process, the body fit without bone
scales (``smpl_fit.w_bone_scale=0``, "before") and with the default ones ("after"), and
reports for both:

* where there is truth: MPJPE of the RTS joints, step I and SMPL + VAE (measured joints);
* always: the floor (:mod:`pipeline.fit.floor`: the best skeleton of constant bone
  lengths fitted to the RTS joints), step I's and SMPL + VAE's distance to those joints
  (median over person-frames of the mean joint distance), SMPL + VAE's joint-limit
  violations per 1,000 bodies, and on Shelf the protocol's PCP of RTS, step I and
  SMPL + VAE;
* the fit's throughput (person-frames fitted per second, both fits, median of
  ``--repeats`` runs of :func:`pipeline.fit.smpl.fit_sequence` on the case's RTS
  tracks), before and after, and their ratio.

Cases: CMU 131_01 (walk) and 131_03 (hop) synthesised on the real Campus rig (3
cameras, 2 people) and on the Pose2Sim demo's rig (4 cameras, 1 person), 150 frames,
default detector noise, made here (``mvviz synth --motion``); Pose2Sim's real balancing
trial (the shipped sample, no truth); the real Shelf sequence when ``../shared/data``
has it (skipped otherwise).

Usage:
    python bench/bench_bodies.py [--repeats N] [--json FILE] [--docs]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import markdown_table, publish, write_json  # noqa: E402
from pipeline.body.model import load_body_model  # noqa: E402
from pipeline.config import PipelineConfig  # noqa: E402
from pipeline.data.joint_sets import get_joint_set  # noqa: E402
from pipeline.data.scene import load_scene  # noqa: E402
from pipeline.evaluation.evaluate import evaluate, fit_distances, stage_tracks  # noqa: E402
from pipeline.evaluation.protocol import (  # noqa: E402
    estimates_by_frame,
    read_protocol_gt,
    score_protocol,
)
from pipeline.fit.prior import load_prior  # noqa: E402
from pipeline.fit.smpl import fit_sequence  # noqa: E402
from pipeline.run.bodies import input_noise  # noqa: E402
from pipeline.run.pipeline import run_pipeline  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SHELF = REPO.parent / "shared" / "data" / "shelf_real"
CMU = REPO / "sample_data" / "mocap" / "cmu131"
RIGS = {
    "Campus": "campus",
    "Pose2Sim": str(REPO / "sample_data" / "pose2sim_demo" / "cameras.json"),
}
BEFORE = ["smpl_fit.w_bone_scale=0"]


def synth_cases(work: Path, frames: int) -> list[tuple[str, Path]]:
    """The CMU clips on the two rigs, synthesised into ``work``."""
    from mvviz.cli import main as mvviz

    out = []
    for rig_name, rig in RIGS.items():
        people = "2" if rig_name == "Campus" else "1"
        for clip in ("131_01", "131_03"):
            path = work / f"cmu_{clip}_{rig_name.lower()}"
            args = [
                "synth", str(path), "--rig", rig, "--motion", str(CMU / f"{clip}.bvh"),
                "--people", people, "--frames", str(frames), "--no-video", "--overwrite",
            ]  # fmt: skip
            assert mvviz(args) == 0, args
            out.append((f"CMU {clip}, {rig_name} rig", path))
    return out


def shelf_case(work: Path) -> tuple[str, Path] | None:
    if not (SHELF / "openpose").is_dir():
        print(f"skipped Shelf: {SHELF} is absent")
        return None
    from pipeline.importers import convert_scene

    path = convert_scene(
        calib_format="pose2sim", calib_paths=[SHELF / "Calib.toml"], out_dir=work / "shelf",
        detections_format="openpose", detections_path=SHELF / "openpose",
    )  # fmt: skip
    return "Shelf (real OpenPose)", Path(path)


def throughput(results, config, model, repeats: int) -> float:
    """Person-frames per second of both fits (median of ``repeats`` runs)."""
    prior = load_prior(config.pose_prior or None) if config.use_pose_prior else None
    rows = int(np.isfinite(results.track_smoothed).all(-1).any(-1).sum())
    noise = input_noise(results)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fit_sequence(results.track_smoothed, results.joint_set, model, prior=prior,
                     params=config.smpl_fit, noise_mm=noise, progress=False)  # fmt: skip
        times.append(time.perf_counter() - t0)
    return rows / float(np.median(times))


def measure(name: str, path: Path, model, repeats: int) -> dict:
    scene = load_scene(path)
    out = {"case": name}
    for label, sets in (("before", BEFORE), ("after", [])):
        config = PipelineConfig().with_overrides(sets)
        res = run_pipeline(scene, config, model, progress=False)
        dist = fit_distances(res)
        row = {k: round(v, 2) for k, v in dist["all"].items()}
        # the person seen longest (the subject of the balancing trial, beside a partly
        # seen second person)
        main = int(np.argmax(np.isfinite(res.track_smoothed).all(-1).any(-1).sum(1)))
        row.update({f"main_{k}": round(v, 2) for k, v in dist[str(main)].items()})
        ev = evaluate(scene, res)
        if ev.stages:
            row.update({f"mpjpe_{k}": round(ev.stages[k]["mpjpe"], 2)
                        for k in ("rts", "smpl", "smpl_vae")})  # fmt: skip
        row["limit_violations_vae"] = round(
            ev.plausibility["smpl_vae"]["limit_violations_per_1000"], 1
        )
        if name.startswith("Shelf"):
            truth = read_protocol_gt(SHELF / "gt_shelf15.npz")
            js = get_joint_set(res.joint_set)
            for k, tracks in stage_tracks(res).items():
                if k in ("rts", "smpl", "smpl_vae"):
                    row[f"pcp_{k}"] = round(
                        100 * score_protocol(estimates_by_frame(tracks, js), truth).average, 2
                    )
        row["fit_person_frames_per_s"] = round(throughput(res, config, model, repeats), 1)
        out[label] = row
    out["throughput_ratio"] = round(
        out["after"]["fit_person_frames_per_s"] / out["before"]["fit_person_frames_per_s"], 3
    )
    return out


def table(rows: list[dict]) -> str:
    head = ["case", "fit", "RTS mm", "step I mm", "SMPL+VAE mm", "floor / step I / VAE (to RTS)",
            "the same, person seen longest", "limit viol./1000", "PCP RTS / I / VAE",
            "fit person-frames/s"]  # fmt: skip
    body = []
    for r in rows:
        for label in ("before", "after"):
            x = r[label]
            g = lambda k, x=x: "-" if k not in x else f"{x[k]:.1f}"  # noqa: E731
            pcp = (
                "-"
                if "pcp_rts" not in x
                else f"{x['pcp_rts']:.2f} / {x['pcp_smpl']:.2f} / {x['pcp_smpl_vae']:.2f}"
            )
            trio = lambda p, g=g: f"{g(p + 'floor')} / {g(p + 'smpl')} / {g(p + 'smpl_vae')}"  # noqa: E731
            body.append([r["case"], "no scales" if label == "before" else "bone scales",
                         g("mpjpe_rts"), g("mpjpe_smpl"), g("mpjpe_smpl_vae"), trio(""),
                         trio("main_"), g("limit_violations_vae"), pcp,
                         g("fit_person_frames_per_s")])  # fmt: skip
    return markdown_table(head, body)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--docs", action="store_true", help="write the documentation's section")
    args = ap.parse_args()
    model = load_body_model()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        cases = synth_cases(work, args.frames)
        cases.append(("Pose2Sim balancing (real)", REPO / "sample_data" / "pose2sim_balancing"))
        shelf = shelf_case(work)
        if shelf is not None:
            cases.append(shelf)
        for name, path in cases:
            r = measure(name, path, model, args.repeats)
            rows.append(r)
            print(f"{name}: before {r['before']}\n  after {r['after']}\n  throughput ratio "
                  f"{r['throughput_ratio']}", flush=True)  # fmt: skip
    text = table(rows)
    print(text)
    if args.json:
        write_json(args.json, {"cases": rows})
    if args.docs:
        ratios = ", ".join(f"{r['throughput_ratio']:.2f}" for r in rows)
        body = (
            "The body fit without bone scales and with them (the default), in the same run. "
            "MPJPE columns against the truth of the synthesised scenes (measured joints); "
            'the "to RTS" columns are the median over person-frames of the mean joint '
            "distance to the RTS joints the fits are given (all people, then the person "
            "seen longest), the floor being the best skeleton of constant bone lengths "
            "(how far the input itself is from rigid). "
            "Limit violations: SMPL + VAE. PCP: the Shelf protocol (actors 1 and 3 in the "
            "frames the shared data holds).\n\n" + text + "\n\n"
            f"Fit throughput with bone scales over without (each case): {ratios}."
        )
        publish("bench_bodies", "Bodies of real proportions", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
