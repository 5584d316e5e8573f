"""Peer benchmark: our 3D against Pose2Sim's on Pose2Sim's real balancing trial.

Input: sample_data/pose2sim_balancing (4 Qualisys cameras, 100 frames at 60 fps, one
subject balancing, bystanders in cameras 1-2), built by tools/make_pose2sim_balancing.py.
Pose2Sim's own results of exactly the shipped OpenPose BODY_25B 2D are the scene's
reference tracks: ``pose2sim`` (raw triangulation) and ``pose2sim_butterworth`` (its
6 Hz Butterworth filter). There is no marker ground truth: the figures say how two
tools agree on one input, and how well each explains the 2D.

Reported, in one run:

 1. per keypoint, the median distance (mm, over the 100 frames) between our subject track
    (the one nearest Pose2Sim's result) and Pose2Sim's: our raw vs its raw, our Kalman
    forward and RTS vs its raw and Butterworth;
 2. per camera, the reprojection error (px, median and mean over the subject's keypoints
    with confidence >= 0.3, Pose2Sim's likelihood threshold) of each result onto the same
    2D: the detections our association gave the subject in that camera;
 3. the fitted SMPL bodies (step I and SMPL + VAE): their keypoints' reprojection error
    as above, their median pixel distance (per camera) and millimetre distance (per
    keypoint) to the RTS joints they were fitted to; and two floors for any body of
    constant proportions: the same fit with its regularisers off (no smoothness, pose,
    free-joint or limit terms) and 600 iterations, the best such body we found, the same
    with an offset for every keypoint (limb joints too, ``FitParams.limb_offsets``; also
    without the head points), and the rigid-head floor (the face points and head top of
    the RTS track fitted by one rigid shape per track, any shape: what a rigid head cannot
    get under); beside them, per keypoint, the triangulation's own frame-to-frame jitter
    (raw minus RTS, mm and px) and its reprojection error onto the 2D (px);
 4. with ``--detect`` (needs the ``[video]`` extra): the same from ``mvviz detect``
    (BlazePose) on the trial's real videos instead of the shipped OpenPose 2D, on the
    keypoints both layouts share, and the detector's run time.

Pose2Sim itself is not run here: ``pip install pose2sim`` pulls OpenSim, onnxruntime,
openvino, PySide6 and opencv-contrib-python (which replaces our opencv-python-headless),
so it cannot be an optional extra of this package; its result of the same input, from its
own repository, is the peer instead.

Usage:
    python bench/bench_peer_pose2sim.py [--detect] [--json FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import markdown_table, publish, write_json  # noqa: E402
from bench.peer_compare import (  # noqa: E402
    per_joint_median_mm,
    reprojection_errors,
    subject_observations,
)
from pipeline.body.model import load_body_model  # noqa: E402
from pipeline.config import PipelineConfig  # noqa: E402
from pipeline.data.joint_sets import mapping_indices  # noqa: E402
from pipeline.data.scene import Scene, load_scene  # noqa: E402
from pipeline.fit.smpl import FitParams, fit_sequence, plausibility  # noqa: E402
from pipeline.results.store import PipelineResults  # noqa: E402
from pipeline.run.pipeline import run_pipeline  # noqa: E402

UNREGULARISED = FitParams(iters=600, w_smooth=0.0, w_pose=0.0, w_free=0.0, w_limit=0.0)
"""The fit with nothing but the data term (betas and offsets still L2-regularised) and
5x the iterations: the closest body of constant proportions we found."""
EVERY_OFFSET = dataclasses.replace(UNREGULARISED, limb_offsets=True)
"""The same with an offset for every keypoint (limb joints too, ``FitParams.limb_offsets``),
each in its parent body part's frame: the floor of a body of constant proportions and
constant keypoint-to-model offsets (MoSh's marker model)."""
HEAD_POINTS = ("nose", "left_eye", "right_eye", "left_ear", "right_ear", "head_top")

TRIAL = Path(__file__).resolve().parents[1] / "sample_data" / "pose2sim_balancing"


def in_joint_set(points: np.ndarray, src, dst) -> np.ndarray:
    """(F, src.J, 3) -> (F, dst.J, 3) by joint name, NaN where ``src`` lacks a joint."""
    s, d = mapping_indices(src, dst)
    out = np.full(points.shape[:-2] + (dst.num_joints, 3), np.nan)
    out[..., d, :] = points[..., s, :]
    return out


def rigid_floor_mm(points: np.ndarray, iters: int = 50) -> np.ndarray:
    """(F, P) distances (mm) of ``points`` (F, P, 3) to the best rigid motion of one
    shape (generalised Procrustes: any constant shape, a rotation and translation per
    frame); frames with a missing point are left out (NaN)."""
    out = np.full(points.shape[:2], np.nan)
    ok = np.isfinite(points).all((1, 2))
    X = points[ok]
    shape = X[0] - X[0].mean(0)
    for _ in range(iters):
        c = X.mean(1, keepdims=True)
        H = np.einsum("pa,fpb->fab", shape, X - c)  # Kabsch of the shape onto each frame
        U, _, Vt = np.linalg.svd(H)
        d = np.sign(np.linalg.det(np.swapaxes(Vt, 1, 2) @ np.swapaxes(U, 1, 2)))
        S = np.tile(np.eye(3), (len(X), 1, 1))
        S[:, 2, 2] = d
        R = np.swapaxes(Vt, 1, 2) @ S @ np.swapaxes(U, 1, 2)  # (F, 3, 3)
        fit = np.einsum("fab,pb->fpa", R, shape) + c
        shape = np.einsum("fba,fpb->fpa", R, X - c).mean(0)  # the shape, re-estimated
    out[ok] = np.linalg.norm(fit - X, axis=-1)
    return out


def px_to(scene: Scene, a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """Per camera: median pixel distance between the projections of (F, J, 3) a and b."""
    out = {}
    for cam in scene.rig:
        d = cam.project(a.reshape(-1, 3)) - cam.project(b.reshape(-1, 3))
        out[cam.name] = float(np.nanmedian(np.linalg.norm(d, axis=-1)))
    return out


def floors(scene: Scene, results: PipelineResults, track: int, model) -> dict:
    """How close a body of constant proportions gets to the subject's RTS joints, and what
    the triangulation itself does at each keypoint (its frame-to-frame jitter: raw minus
    RTS; its reprojection error onto the 2D)."""
    rts, raw = results.track_smoothed[track], results.track_raw[track]
    names = scene.joint_set.names
    head = [names.index(n) for n in HEAD_POINTS if n in names]
    body = [j for j in range(len(names)) if j not in head]
    out = {}
    for tag, params in (("unregularised", UNREGULARISED), ("every_offset", EVERY_OFFSET)):
        fit, _ = fit_sequence(rts[None], results.joint_set, model, params=params,
                              progress=False)  # fmt: skip
        kp = fit.keypoints[0]
        out[f"{tag}_px"] = px_to(scene, kp, rts)
        out[f"{tag}_no_head_px"] = px_to(scene, kp[:, body], rts[:, body])
        out[f"{tag}_mm"] = float(np.nanmedian(fit.residual))
        out[f"{tag}_seconds"] = fit.seconds
        out[f"{tag}_limit_violations_per_1000"] = plausibility(fit)["limit_violations_per_1000"]
        out[f"{tag}_per_keypoint_mm"] = dict(
            zip(names, np.nanmedian(np.linalg.norm(kp - rts, axis=-1), 0).tolist(), strict=True)
        )
    _, _, obs = subject_observations(scene, results, scene.references["pose2sim"].joints)
    e2d = reprojection_errors(scene.rig, raw, obs.keypoints)  # (F, V, J) px
    out["raw_jitter_mm"] = dict(
        zip(names, np.nanmedian(np.linalg.norm(raw - rts, axis=-1), 0).tolist(), strict=True)
    )
    out["raw_jitter_px"] = px_to(scene, raw, rts)
    out["raw_2d_px"] = dict(zip(names, np.nanmedian(e2d, (0, 1)).tolist(), strict=True))
    if len(head) >= 3:
        r = rigid_floor_mm(rts[:, head])
        out["rigid_head_mm"] = {names[i]: float(np.nanmedian(r[:, k])) for k, i in enumerate(head)}
    return out


def compare(scene: Scene, results: PipelineResults, refs: dict[str, np.ndarray]) -> dict:
    raw_ref = refs["pose2sim"]
    track, dist, obs = subject_observations(scene, results, raw_ref)
    ours = {
        "ours raw": results.track_raw[track],
        "ours kalman": results.track_forward[track],
        "ours rts": results.track_smoothed[track],
    }
    for stage in ("smpl", "smpl_vae"):  # the fitted bodies' keypoints, where there are fits
        fit = getattr(results, stage)
        if fit is not None:
            ours[f"ours {stage} body"] = fit.keypoints[track]
    pairs = [
        ("ours raw", "pose2sim"),
        ("ours kalman", "pose2sim"),
        ("ours rts", "pose2sim_butterworth"),
        ("ours raw", "pose2sim_butterworth"),
    ]
    per_joint = {f"{a} vs {b}": per_joint_median_mm(ours[a], refs[b]) for a, b in pairs}
    reproj = {}
    for name, pts in {**ours, **refs}.items():
        e = reprojection_errors(scene.rig, pts, obs.keypoints)
        reproj[name] = {
            cam.name: (float(np.nanmedian(e[:, v])), float(np.nanmean(e[:, v])))
            for v, cam in enumerate(scene.rig)
        }
    # The fitted bodies against the triangulated joints they were fitted to (RTS), in px.
    bodies = [n for n in ours if n.endswith(" body")]
    body_vs_joints = {name: px_to(scene, ours[name], ours["ours rts"]) for name in bodies}
    names = scene.joint_set.names
    body_mm = {
        name: np.nanmedian(np.linalg.norm(ours[name] - ours["ours rts"], axis=-1), 0)
        for name in bodies
    }
    return {
        "body_vs_rts_px": body_vs_joints,
        "body_vs_rts_mm": {
            name: {n: float(v[j]) for j, n in enumerate(names) if np.isfinite(v[j])}
            for name, v in body_mm.items()
        },
        "track": track,
        "frames": int(np.isfinite(results.track_raw[track, :, :, 0]).any(1).sum()),
        "median_mm": dist,
        "per_joint_mm": {
            k: {n: float(v[j]) for j, n in enumerate(names) if np.isfinite(v[j])}
            for k, v in per_joint.items()
        },
        "reprojection_px": reproj,
    }


def print_report(title: str, fig: dict) -> None:
    print(
        f"\n== {title}: subject = track {fig['track']} ({fig['frames']} frames), "
        f"median {fig['median_mm']:.1f} mm from Pose2Sim's raw result"
    )
    cols = list(fig["per_joint_mm"])
    w = max(len(c) for c in cols) + 3
    names = list(next(iter(fig["per_joint_mm"].values())))
    print(f"{'keypoint (mm)':<18}" + "".join(f"{c:>{w}}" for c in cols))
    for n in names:
        print(
            f"{n:<18}" + "".join(f"{fig['per_joint_mm'][c].get(n, np.nan):>{w}.1f}" for c in cols)
        )
    print(
        f"{'median':<18}"
        + "".join(f"{np.median(list(fig['per_joint_mm'][c].values())):>{w}.1f}" for c in cols)
    )
    cams = list(next(iter(fig["reprojection_px"].values())))
    print(f"\n{'reprojection px (median / mean)':<34}" + "".join(f"{c:>16}" for c in cams))
    for name, per_cam in fig.get("body_vs_rts_px", {}).items():
        print(
            f"{name + ' vs rts joints':<34}" + "".join(f"{per_cam[c]:>9.1f}       " for c in cams)
        )
    fl = fig.get("floors")
    if fl:
        for key, label in (
            ("unregularised_px", "unregularised body vs rts joints"),
            ("every_offset_px", "  + every keypoint an offset"),
            ("every_offset_no_head_px", "    the same without the head"),
            ("raw_jitter_px", "ours raw vs rts (jitter)"),
        ):
            per_cam = fl[key]
            print(f"{label:<34}" + "".join(f"{per_cam[c]:>9.1f}       " for c in cams))
    for name, per_cam in fig["reprojection_px"].items():
        print(
            f"{name:<34}" + "".join(f"{per_cam[c][0]:>9.1f} /{per_cam[c][1]:>5.1f}" for c in cams)
        )
    if fig.get("body_vs_rts_mm"):
        bodies = list(fig["body_vs_rts_mm"])
        extra = (("every_offset_per_keypoint_mm", "every-offset floor"),
                 ("raw_jitter_mm", "raw vs rts mm"), ("raw_2d_px", "raw vs 2D px"),
                 ("rigid_head_mm", "rigid-head floor"))  # fmt: skip
        extra = [(k, t) for k, t in extra if k in (fl or {})]
        print(f"\n{'body keypoint vs rts (mm)':<26}" + "".join(f"{b:>20}" for b in bodies)
              + "".join(f"{t:>20}" for _, t in extra))  # fmt: skip
        for n in fig["body_vs_rts_mm"][bodies[0]]:
            row = "".join(f"{fig['body_vs_rts_mm'][b].get(n, np.nan):>20.1f}" for b in bodies)
            row += "".join(f"{fl[k][n]:>20.1f}" if n in fl[k] else " " * 20 for k, _ in extra)
            print(f"{n:<26}" + row)
        meds = "".join(
            f"{np.median(list(fig['body_vs_rts_mm'][b].values())):>20.1f}" for b in bodies
        )
        print(f"{'median':<26}" + meds)
    if fl:
        for tag, label in (("unregularised", "unregularised fit"),
                           ("every_offset", "the same, every keypoint an offset")):  # fmt: skip
            print(
                f"{label} ({UNREGULARISED.iters} iterations, {fl[tag + '_seconds']:.1f} s): "
                f"median {fl[tag + '_mm']:.1f} mm from the rts joints, "
                f"{fl[tag + '_limit_violations_per_1000']:.0f} joint-limit violations per "
                "1,000 bodies"
            )


def run_detect(scene: Scene) -> tuple[Scene, float]:
    """``mvviz detect`` (BlazePose) on the trial's real videos, in a scratch scene."""
    from pipeline.detect.video import detect_scene  # the [video] extra

    tmp = Path(tempfile.mkdtemp(prefix="peer_detect_"))
    shutil.copyfile(scene.root / "cameras.json", tmp / "cameras.json")
    t0 = time.perf_counter()
    detect_scene(tmp, [scene.root / "videos"], progress=True)
    seconds = time.perf_counter() - t0
    return load_scene(tmp), seconds


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--detect", action="store_true", help="also run mvviz detect on the videos")
    ap.add_argument("--json", type=Path, help="write the figures here")
    ap.add_argument("--docs", action="store_true", help="write the documentation's section")
    args = ap.parse_args()

    warnings.simplefilter("ignore")
    scene = load_scene(TRIAL)
    model = load_body_model()
    config = PipelineConfig()
    refs = {n: r.joints for n, r in scene.references.items()}
    t0 = time.perf_counter()
    results = run_pipeline(scene, config, model, progress=False)
    seconds = time.perf_counter() - t0
    figures = {"openpose_2d": compare(scene, results, refs)}
    figures["openpose_2d"]["pipeline_s"] = seconds
    if results.smpl is not None:
        figures["openpose_2d"]["floors"] = floors(
            scene, results, figures["openpose_2d"]["track"], model
        )
    print_report(
        f"shipped OpenPose BODY_25B 2D ({seconds:.2f} s, all stages)", figures["openpose_2d"]
    )

    if args.detect:
        det_scene, det_s = run_detect(scene)
        det_results = run_pipeline(det_scene, config, model, progress=False)
        det_refs = {
            n: in_joint_set(r, scene.joint_set, det_scene.joint_set) for n, r in refs.items()
        }
        fig = compare(det_scene, det_results, det_refs)
        fig["detect_s"] = det_s
        figures["blazepose_2d"] = fig
        print_report(f"mvviz detect (BlazePose) on the real videos ({det_s:.0f} s)", fig)
    if args.json:
        write_json(args.json, figures)
    if args.docs:
        publish("bench_peer_pose2sim", "Pose2Sim's balancing trial: ours against Pose2Sim",
                docs_section(figures))  # fmt: skip
    return 0


def docs_section(figures: dict) -> str:
    """The Benchmarks page's section: distances to Pose2Sim's result, reprojection."""
    parts = []
    for key, title in (("openpose_2d", "the shipped OpenPose BODY_25B 2D"),
                       ("blazepose_2d", "`mvviz detect` (BlazePose) on the videos")):  # fmt: skip
        fig = figures.get(key)
        if fig is None:
            continue
        cams = list(next(iter(fig["reprojection_px"].values())))
        rows = [[name, *(f"{per_cam[c][0]:.1f} / {per_cam[c][1]:.1f}" for c in cams)]
                for name, per_cam in fig["reprojection_px"].items()]  # fmt: skip
        medians = {c: float(np.median(list(v.values()))) for c, v in fig["per_joint_mm"].items()}
        parts.append(
            f"**From {title}**: the subject is track {fig['track']} over {fig['frames']} "
            f"frames; median distance per keypoint to Pose2Sim's result of the same input: "
            + ", ".join(f"{c} {m:.1f} mm" for c, m in medians.items())
            + ".\n\nReprojection onto the subject's 2D, median / mean px:\n\n"
            + markdown_table(["result", *cams], rows)
        )
    return "\n\n".join(parts)


if __name__ == "__main__":
    raise SystemExit(main())
