"""Benchmark the SMPL fit: batched warm-started fit vs a plain per-frame LBFGS fit.

On the shipped sample scene (sample_data/shelf_synth; the pipeline is run first if its
results file is missing or stale), fits every track of the configured Kalman output
(``results.track_smoothed``, COCO-17, as ``fit_bodies``) with
:func:`pipeline.fit.smpl.fit_sequence`: step I and the VAE-corrected fit with the
shipped prior. Reports person-frames fitted per second and the mean joint residual
(mm), then, in the same run, the baseline on
``--baseline-frames`` person-frames spread over the sequence: one frame at a time, the
full mesh model (``BodyModel.forward``: LBS of all 13,348 vertices, then the COCO
regressor), pose / betas / translation from the closed-form root alignment and the rest
pose (no warm start from other frames, no batching), torch LBFGS with strong-Wolfe line
search, same Smooth L1 data term and pose / betas regularisers. Both use one torch
thread (FitParams.num_threads). Also prints MPJPE against the ground truth and the
plausibility figures of every stage.

With ``--chunk C`` also the chunked fit (:func:`pipeline.fit.chunks.fit_in_chunks`,
chunks of C frames warm-started by the previous one), its accuracy in the table, and
its throughput at 20 tracks (the sample's 4 tracks copied 5 times: a 31 x 20 scene's
chunk size in rows; the copies' figures are the same fits, only the cost is new),
alternated with the whole-sequence fit of the same 20 tracks, CPU time.

Usage:
    python bench/bench_fit.py [--baseline-frames N] [--chunk C] [--json FILE]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import markdown_table, publish, write_json  # noqa: E402
from pipeline.body import pose_limits  # noqa: E402
from pipeline.body.kinematics import keypoint_buffers, matrix_to_rotvec  # noqa: E402
from pipeline.body.model import load_body_model  # noqa: E402
from pipeline.config import PipelineConfig  # noqa: E402
from pipeline.data.scene import load_scene  # noqa: E402
from pipeline.evaluation.evaluate import (  # noqa: E402
    ground_truth_slots,
    gt_per_frame,
    stage_metrics,
    to_smpl_slots,
)
from pipeline.fit.chunks import fit_in_chunks  # noqa: E402
from pipeline.fit.prior import load_prior  # noqa: E402
from pipeline.fit.smpl import (  # noqa: E402
    FitParams,
    _pack,
    fit_sequence,
    initial_alignment,
    plausibility,
)
from pipeline.run.bodies import input_noise  # noqa: E402
from pipeline.run.pipeline import run_or_load  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def baseline_fit(model, targets_mm: np.ndarray, params: FitParams, max_iter: int = 100):
    """Plain per-frame fit: (J, 3) mm target -> (residual mm (J,), seconds)."""
    t0 = time.perf_counter()
    prob = _pack(targets_mm[None, None], None)
    buf = keypoint_buffers(model, "coco17")
    R0, t_init = initial_alignment(prob, buf)
    pose = torch.zeros(1, 24, 3)
    pose[0, 0] = torch.as_tensor(matrix_to_rotvec(R0[0]), dtype=torch.float32)
    pose.requires_grad_(True)
    betas = torch.zeros(1, 10, requires_grad=True)
    transl = torch.as_tensor(t_init, dtype=torch.float32).requires_grad_(True)
    target, weight = prob.target, prob.weight
    w_joint = params.w_pose + params.w_free * buf.free_weight
    w_joint[0] = 0.0

    def loss_fn():
        out = model(pose, betas, transl)  # full LBS over every vertex
        kp = model.coco_keypoints(out.vertices)
        r = torch.nn.functional.smooth_l1_loss(
            kp, target, reduction="none", beta=params.smooth_l1_beta_m
        )
        loss = (r.sum(-1) * weight).sum() / (3 * weight.sum())
        loss = loss + params.w_betas * (betas * betas).mean()
        # |R - I|_F^2 = 4 (1 - cos angle) ~ angle^2 for the small regulariser
        ang2 = (pose[0] * pose[0]).sum(-1)
        return loss + (4 * (1 - torch.cos(ang2.clamp_min(1e-12).sqrt())) * w_joint).sum()

    opt = torch.optim.LBFGS(
        [pose, betas, transl],
        lr=1.0,
        max_iter=max_iter,
        history_size=20,
        tolerance_grad=1e-9,
        tolerance_change=1e-12,
        line_search_fn="strong_wolfe",
    )

    def closure():
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        kp = model.coco_keypoints(model(pose, betas, transl).vertices)[0].numpy() * 1000.0
    res = np.linalg.norm(kp - targets_mm, axis=-1)
    return res, time.perf_counter() - t0


def rows(name: str, scored: np.ndarray, gt_dense: np.ndarray, plaus: dict) -> tuple[str, dict]:
    m, _ = stage_metrics(scored, gt_dense)
    return name, {"mpjpe_mm": m["mpjpe"], "accel_mm": m["accel"], "recall": m["recall"], **plaus}


def chunked_figures(tracks, js, model, prior, params, chunk: int, repeats: int = 3) -> dict:
    """The chunked fit on the sample (its fits, for the table) and, alternated with the
    whole-sequence fit, step I's CPU throughput on the tracks copied to 20."""
    t0 = time.process_time()
    c1, c2 = fit_in_chunks(tracks, js, model, prior=prior, params=params, chunk_frames=chunk,
                           progress=False)  # fmt: skip
    cpu = time.process_time() - t0
    n = int(c1.present.sum())
    print(f"chunks of {chunk} frames, step I + VAE: {n / cpu:7.1f} person-frames/CPU-s, "
          f"residual step I {np.nanmean(c1.residual):.2f} mm, VAE {np.nanmean(c2.residual):.2f}"
          " mm")  # fmt: skip
    wide = np.concatenate([tracks] * 5)
    cost = {"whole": [], "chunks": []}
    nw = 0
    for _ in range(repeats):
        for name in cost:
            t0 = time.process_time()
            if name == "whole":
                f, _ = fit_sequence(wide, js, model, params=params, progress=False)
            else:
                f, _ = fit_in_chunks(wide, js, model, params=params, chunk_frames=chunk,
                                     progress=False)  # fmt: skip
            cost[name].append(time.process_time() - t0)
            nw = int(f.present.sum())
    rate = {k: nw / float(np.median(v)) for k, v in cost.items()}
    print(f"step I at 20 tracks ({nw} person-frames), median of {repeats} alternated, CPU: "
          f"whole sequence {rate['whole']:.1f}, chunks of {chunk} {rate['chunks']:.1f} "
          "person-frames/CPU-s")  # fmt: skip
    return {
        "chunk_frames": chunk, "chunked_step1_vae_pf_per_cpu_s": n / cpu,
        "chunked_step1_residual_mm": float(np.nanmean(c1.residual)),
        "chunked_vae_residual_mm": float(np.nanmean(c2.residual)),
        "step1_pf_per_cpu_s_20_tracks": rate,
        "fits": {"smpl_chunks": c1, "smpl_vae_chunks": c2},
        "fit_objects": {"smpl_chunks": c1, "smpl_vae_chunks": c2},
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scene", type=Path, default=REPO / "sample_data" / "shelf_synth")
    parser.add_argument("--baseline-frames", type=int, default=24)
    parser.add_argument("--chunk", type=int, default=0, help="also the fit in chunks of C frames")
    parser.add_argument("--json", type=Path, help="also write the figures to this JSON file")
    parser.add_argument("--docs", action="store_true", help="write the documentation's section")
    args = parser.parse_args()

    scene = load_scene(args.scene)
    model = load_body_model()
    results, _ = run_or_load(scene, PipelineConfig(), model, progress=False)
    tracks, js = results.track_smoothed, results.joint_set  # what fit_bodies fits
    prior = load_prior()
    params = FitParams()
    fit_sequence(tracks[:, :3], js, model, params=params, progress=False)  # warm-up, buffers
    t0 = time.perf_counter()
    noise = input_noise(results)  # as fit_bodies: each track's smoothing follows its noise
    fit1, fit2 = fit_sequence(tracks, js, model, prior=prior, params=params, noise_mm=noise,
                              progress=False)  # fmt: skip
    total = time.perf_counter() - t0
    n = int(fit1.present.sum())
    fast = {
        "person_frames": n,
        "step1_pf_per_s": n / fit1.seconds,
        "step1_residual_mm": float(np.nanmean(fit1.residual)),
        "vae_stage_pf_per_s": n / fit2.seconds,
        "vae_residual_mm": float(np.nanmean(fit2.residual)),
        "total_pf_per_s": n / total,
        "total_seconds": total,
    }
    # Baseline on person-frames spread over the sequence.
    k_idx, f_idx = np.nonzero(fit1.present)
    pick = np.linspace(0, len(k_idx) - 1, args.baseline_frames).round().astype(int)
    old = torch.get_num_threads()
    torch.set_num_threads(params.num_threads or old)
    try:
        res, secs = [], []
        for i in pick:
            r, s = baseline_fit(model, tracks[k_idx[i], f_idx[i]], params)
            res.append(r)
            secs.append(s)
    finally:
        torch.set_num_threads(old)
    res = np.concatenate(res)
    base = {
        "person_frames": len(pick),
        "pf_per_s": len(pick) / float(np.sum(secs)),
        "residual_mm": float(np.nanmean(res)),
        "step1_residual_same_frames_mm": float(np.nanmean(fit1.residual[k_idx[pick], f_idx[pick]])),
    }
    ratio = fast["step1_pf_per_s"] / base["pf_per_s"]
    print(
        f"batched fit, step I : {fast['step1_pf_per_s']:7.1f} person-frames/s  "
        f"mean residual {fast['step1_residual_mm']:5.1f} mm  ({n} person-frames)"
    )
    print(
        f"VAE correction      : {fast['vae_stage_pf_per_s']:7.1f} person-frames/s  "
        f"mean residual {fast['vae_residual_mm']:5.1f} mm"
    )
    print(f"step I + VAE        : {fast['total_pf_per_s']:7.1f} person-frames/s  ({total:.1f} s)")
    print(
        f"per-frame LBFGS     : {base['pf_per_s']:7.2f} person-frames/s  mean residual "
        f"{base['residual_mm']:5.1f} mm (step I on the same frames: "
        f"{base['step1_residual_same_frames_mm']:.1f} mm)"
    )
    print(f"speed-up step I / baseline: {ratio:.1f}x")
    chunked = chunked_figures(tracks, js, model, prior, params, args.chunk) if args.chunk else {}

    gt_slots, _ = ground_truth_slots(scene.gt, js)
    gt_dense, _ = gt_per_frame(scene.gt, gt_slots, results.num_frames)
    # Scored like pipeline.evaluation.evaluate: where the raw triangulation has the joint.
    measured = np.isfinite(results.track_raw).all(-1, keepdims=True)

    def scored(x: np.ndarray) -> np.ndarray:
        return to_smpl_slots(np.where(measured, x, np.nan), js)

    skeleton = pose_limits.skeleton_plausibility
    table = dict(
        [
            rows("raw", scored(results.track_raw), gt_dense,
                 skeleton(to_smpl_slots(results.track_raw, js))),
            rows("kalman", scored(tracks), gt_dense, skeleton(to_smpl_slots(tracks, js))),
            rows("smpl", scored(fit1.keypoints), gt_dense, plausibility(fit1)),
            rows("smpl_vae", scored(fit2.keypoints), gt_dense, plausibility(fit2)),
        ]
    )  # fmt: skip
    joints_dense, _ = gt_per_frame(scene.gt, scene.gt.joints3d, results.num_frames)
    for name, fit in chunked.pop("fits", {}).items():
        table[name] = rows(name, scored(fit.keypoints), gt_dense, plausibility(fit))[1]
    fits_by_name = {"smpl": fit1, "smpl_vae": fit2}
    fits_by_name.update({k: v for k, v in chunked.pop("fit_objects", {}).items()})
    for name, fit in fits_by_name.items():
        table[name]["mpjpe_smpl24_joints_mm"] = stage_metrics(fit.joints, joints_dense)[0]["mpjpe"]
    print(f"\n{'stage':9s} {'MPJPE':>7s} {'accel':>6s} {'limits/1k':>9s} {'hinge/1k':>8s} "
          f"{'bone std':>8s} {'foot jit':>8s} {'wrist jit':>9s}")  # fmt: skip
    for name, v in table.items():
        lim = v.get("limit_violations_per_1000", float("nan"))
        print(
            f"{name:9s} {v['mpjpe_mm']:7.2f} {v['accel_mm']:6.2f} {lim:9.1f} "
            f"{v['hinge_violations_per_1000']:8.1f} {v['bone_length_std_mm']:8.2f} "
            f"{v['foot_jitter']:8.2f} {v['wrist_jitter']:9.2f}"
        )
    print("(MPJPE, accel: COCO-17 keypoints vs gt keypoints3d where raw has the joint, mm;"
          " plausibility over whole tracks; SMPL-24 joints vs joints3d, all frames: "
          + ", ".join(f"{k} {table[k]['mpjpe_smpl24_joints_mm']:.2f}" for k in fits_by_name)
          + " mm)")  # fmt: skip
    if args.json:
        out = {"fast": fast, "baseline": base, "speedup": ratio, "stages": table, **chunked}
        write_json(args.json, out)
    if args.docs:
        speed = [
            ["step I (batched, warm-started)", f"{fast['step1_pf_per_s']:.1f}",
             f"{fast['step1_residual_mm']:.1f}", f"**{ratio:.0f}x**"],
            ["step I + VAE correction", f"{fast['total_pf_per_s']:.1f}",
             f"{fast['vae_residual_mm']:.1f}", f"{fast['total_pf_per_s'] / base['pf_per_s']:.0f}x"],
            ["per-frame LBFGS of the full mesh (baseline)", f"{base['pf_per_s']:.2f}",
             f"{base['residual_mm']:.1f}", "1x"],
        ]  # fmt: skip
        quality = [[name, f"{v['mpjpe_mm']:.2f}", f"{v['accel_mm']:.2f}",
                    f"{lim:.1f}" if np.isfinite(lim := v.get("limit_violations_per_1000",
                                                             np.nan)) else "n/a (no rotations)",
                    f"{v['bone_length_std_mm']:.2f}"] for name, v in table.items()]  # fmt: skip
        publish("bench_fit", "SMPL fit", (
            f"The fit on `{args.scene.name}`'s filtered tracks ({n} person-frames), against a "
            f"plain per-frame LBFGS fit on {base['person_frames']} of them.\n\n"
            + markdown_table(["fit", "person-frames/s", "mean residual mm", "speed-up"], speed)
            + "\n\nAgainst the ground truth (COCO-17 keypoints where the raw triangulation "
            "has the joint; plausibility over whole tracks):\n\n"
            + markdown_table(["stage", "MPJPE mm", "accel. error", "limit violations / 1000",
                              "bone length std mm"], quality)))  # fmt: skip


if __name__ == "__main__":
    main()
