"""Benchmark ``mvviz diagnose`` on faults put in on purpose (pipeline.diagnose.perturb).

Scenes: the shipped Shelf scene (default detector noise), its noisy twin, and, for the
checks that need no truth, Pose2Sim's real balancing trial and demo. Prints:

- **sync**: each delay (whole and sub-frame) of one camera, the offset found, its
  error and confidence, the largest false offset of the other cameras; in the same run
  the baseline of Pose2Sim's kind, a cross-correlation of the camera's 2D keypoint speed
  with the other cameras' (integer lag, parabola-refined), on the same scenes;
- **late camera vs calibration**: for each delay, the calibration suspects as recorded
  and once judged in sync (``pipeline.diagnose.in_sync``: a late camera is out of sync,
  not a suspect);
- **calibration**: a camera rotated 1 degree or moved 5 cm: whether it is named, the
  refined camera's distance from the truth, the raw MPJPE with the true, the wrong and
  the refined calibration;
- **floor**: the shipped and real scenes as they are, and the Shelf scene turned z-down
  and y-up: up's angle to +z, the floor height, and after the fix;
- the time each diagnosis takes (medians of the runs above).

``--sweep`` instead: camera 1 late by 0..10 whole frames on both scenes, and a drift
(in sync, then 3 frames late) seen per window.

Usage:
    python bench/bench_diagnose.py [--json FILE] [--quick | --sweep]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import write_json  # noqa: E402
from pipeline.body.model import load_body_model  # noqa: E402
from pipeline.config import PipelineConfig  # noqa: E402
from pipeline.data.scene import load_scene  # noqa: E402
from pipeline.diagnose.calibration import check_calibration, replace_camera  # noqa: E402
from pipeline.diagnose.floor import estimate_floor, transform_scene  # noqa: E402
from pipeline.diagnose.in_sync import check_calibration_in_sync  # noqa: E402
from pipeline.diagnose.perturb import _concat, delay_camera, perturb_camera_pose  # noqa: E402
from pipeline.diagnose.reference import camera_detections  # noqa: E402
from pipeline.diagnose.sync import estimate_offsets, offsets_over_windows  # noqa: E402
from pipeline.evaluation.evaluate import evaluate  # noqa: E402
from pipeline.run.pipeline import run_pipeline  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CONFIG = PipelineConfig(fit_smpl=False)
TIMES: dict[str, list[float]] = {"sync": [], "calibration": [], "floor": [], "in sync": []}


def run(scene):
    return run_pipeline(scene, CONFIG, MODEL, progress=False)


def timed(kind, fn, *a, **kw):
    t = time.perf_counter()
    out = fn(*a, **kw)
    TIMES[kind].append(time.perf_counter() - t)
    return out


# --------------------------------------------------------------------------- baseline


def speed_signal(scene, results, view: int) -> np.ndarray:
    """(F,) the camera's mean 2D keypoint speed (px/frame) over its people, each matched
    to its nearest detection in the previous frame; NaN where it saw nobody twice."""
    dets, index = camera_detections(scene, results, view)
    F = dets.shape[0]
    out = np.full(F, np.nan)
    for f in range(1, F):
        a, b = dets[f - 1], dets[f]  # (n, J, 3)
        ok_a, ok_b = index[f - 1] >= 0, index[f] >= 0
        if not ok_a.any() or not ok_b.any():
            continue
        d = np.linalg.norm(b[ok_b, None, :, :2] - a[None, ok_a, :, :2], axis=-1)  # (nb, na, J)
        d = np.nanmedian(np.where(np.isfinite(d), d, np.nan), axis=-1)
        best = np.nanmin(d, axis=1)
        best = best[np.isfinite(best) & (best < 100)]
        if len(best):
            out[f] = best.mean()
    return out


def speed_correlation_offset(scene, results, view: int, max_shift: int) -> float:
    """Pose2Sim-style: the lag maximising the correlation of this camera's keypoint
    speed with the mean of the others' (positive = this camera lags)."""
    sig = [speed_signal(scene, results, v) for v in range(len(scene.rig))]
    ref = np.nanmean([s for v, s in enumerate(sig) if v != view], axis=0)
    me = sig[view]
    shifts = np.arange(-max_shift, max_shift + 1)
    corr = []
    for s in shifts:  # me[g] against ref[g - s]
        g = np.arange(max(0, s), min(len(me), len(me) + s))
        x, y = me[g], ref[g - s]
        ok = np.isfinite(x) & np.isfinite(y)
        corr.append(np.corrcoef(x[ok], y[ok])[0, 1] if ok.sum() > 10 else np.nan)
    corr = np.array(corr)
    k = int(np.nanargmax(corr))
    off = float(shifts[k])
    if 0 < k < len(corr) - 1 and np.isfinite(corr[k - 1 : k + 2]).all():
        a, b, c = -corr[k - 1 : k + 2]
        den = a - 2 * b + c
        off += 0.0 if den <= 0 else float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))
    return off


# --------------------------------------------------------------------------- the checks


def sync_rows(name: str, scene, cases) -> list[dict]:
    rows = []
    for cam, delay in cases:
        sc = delay_camera(scene, cam, delay)
        res = run(sc)
        est = timed("sync", estimate_offsets, sc, res)
        e = est[cam]
        false = max(abs(x.offset_frames) for k, x in est.items() if k != cam)
        base = speed_correlation_offset(sc, res, sc.rig.index_of(cam), 12)
        # The late camera and the calibration check: as recorded, and judged in sync
        # (re-timed by the offsets found; what `mvviz diagnose` reports).
        recorded = check_calibration(sc, res, refine=False)
        in_sync = timed("in sync", check_calibration_in_sync, sc, res, est, refine=False).findings
        rows.append({
            "scene": name, "camera": cam, "delay": delay, "found": e.offset_frames,
            "error": abs(e.offset_frames - delay), "confidence": e.confidence,
            "max_false_offset": false, "speed_corr_found": base,
            "speed_corr_error": abs(base - delay),
            "suspects_as_recorded": [k for k, f in recorded.items() if f.suspect],
            "suspects_in_sync": [k for k, f in in_sync.items() if f.suspect],
            "out_of_sync": [k for k, f in in_sync.items() if f.out_of_sync],
            "systematic_px": [recorded[cam].systematic_px, in_sync[cam].systematic_px],
        })  # fmt: skip
    return rows


def sweep_rows(name: str, scene, camera: str = "1") -> list[dict]:
    """``camera`` late by 0 (in sync) .. 10 whole frames: the offset found, its error,
    confidence, and the other cameras' largest |offset|."""
    rows = []
    for delay in range(11):
        sc = delay_camera(scene, camera, delay) if delay else scene
        est = estimate_offsets(sc, run(sc))
        e = est[camera]
        rows.append({
            "scene": name, "camera": camera, "delay": delay, "found": e.offset_frames,
            "error": abs(e.offset_frames - delay), "confidence": e.confidence,
            "max_false_offset": max(abs(x.offset_frames) for k, x in est.items() if k != camera),
        })  # fmt: skip
    return rows


def drift_row(name: str, scene, camera: str = "1", late: int = 3, at: int = 125) -> dict:
    """``camera`` in sync until frame ``at``, ``late`` frames late after: the offsets per
    window of ``at`` frames (``mvviz diagnose --window``)."""
    det, shifted = scene.detections, delay_camera(scene, camera, late).detections
    v = scene.rig.index_of(camera)
    early = det.take((det.view != v) | (det.frame < at))
    after = shifted.take((shifted.view == v) & (shifted.frame >= at + late))
    drifted = dataclasses.replace(scene, detections=_concat(early, after))
    windows = offsets_over_windows(drifted, run(drifted), window=at)
    return {"scene": name, "camera": camera, "late_after": at, "delay": late,
            "windows": [(a, b, est[camera].offset_frames, est[camera].confidence)
                        for a, b, est in windows]}  # fmt: skip


def calibration_rows(name: str, truth, faults) -> list[dict]:
    rows = []
    mpjpe_true = evaluate(truth, run(truth)).stages["raw"]["mpjpe"]
    for label, kw in faults:
        sc = perturb_camera_pose(truth, "2", **kw)
        res = run(sc)
        found = timed("calibration", check_calibration, sc, res)
        suspects = [k for k, f in found.items() if f.suspect]
        row = {"scene": name, "fault": label, "named": suspects,
               "mpjpe_true": mpjpe_true, "mpjpe_wrong": evaluate(sc, res).stages["raw"]["mpjpe"]}
        f = found["2"]
        if f.refined is not None:
            t = truth.rig[2]
            row["refined_rot_deg"] = float(
                np.degrees(Rotation.from_matrix(f.refined.R @ t.R.T).magnitude())
            )
            row["refined_centre_mm"] = float(np.linalg.norm(f.refined.center - t.center))
            fixed = dataclasses.replace(sc, rig=replace_camera(sc.rig, 2, f.refined))
            row["mpjpe_refined"] = evaluate(fixed, run(fixed)).stages["raw"]["mpjpe"]
        rows.append(row)
    return rows


def floor_rows(scenes: dict) -> list[dict]:
    rows = []
    for name, scene in scenes.items():
        res = run(scene)
        f = timed("floor", estimate_floor, res.track_smoothed, scene.joint_set.names)
        row = {"scene": name, **f.to_dict()}
        if not f.ok and scene.gt is not None:
            fixed = transform_scene(scene, f.fix_transform(), MODEL)
            g = estimate_floor(run(fixed).track_smoothed, scene.joint_set.names)
            row["after_fix"] = g.to_dict()
        rows.append(row)
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--quick", action="store_true", help="fewer cases")
    ap.add_argument(
        "--sweep", action="store_true",
        help="only: camera 1 late by 0..10 frames on both scenes, and a drift by windows",
    )  # fmt: skip
    args = ap.parse_args()
    global MODEL
    MODEL = load_body_model()
    clean = load_scene(REPO / "sample_data" / "shelf_synth")
    noisy = load_scene(REPO / "sample_data" / "shelf_synth_noisy")
    if args.sweep:
        return _sweep(clean, noisy, args.json)
    cases = [("1", 1), ("3", 4), ("0", -7), ("4", 10), ("2", 0.5), ("2", 2.5)]
    if args.quick:
        cases = cases[1:2] + cases[4:5]
    sync = sync_rows("shelf", clean, cases) + sync_rows("shelf noisy", noisy, cases)
    print("sync: delay -> found (error, confidence; largest false offset of the others) | "
          "keypoint-speed correlation")  # fmt: skip
    for r in sync:
        print(f"  {r['scene']:<12} cam {r['camera']} {r['delay']:+5.1f}: {r['found']:+7.3f} "
              f"({r['error']:.3f}, {r['confidence']:.2f}; {r['max_false_offset']:.3f}) | "
              f"{r['speed_corr_found']:+7.3f} ({r['speed_corr_error']:.3f})")  # fmt: skip
    print("late camera and calibration: suspects as recorded -> judged in sync (out of sync); "
          "its systematic residual as recorded -> re-timed")  # fmt: skip
    for r in sync:
        a, b = r["systematic_px"]
        print(f"  {r['scene']:<12} cam {r['camera']} {r['delay']:+5.1f}: "
              f"{r['suspects_as_recorded']} -> {r['suspects_in_sync']} ({r['out_of_sync']}); "
              f"{a:.1f} -> {b:.1f} px")  # fmt: skip
    faults = [("rotated 1 deg", dict(rotation_deg=1.0, axis=(0.3, 1.0, 0.2))),
              ("moved 5 cm", dict(translation_mm=(50.0, 0.0, 0.0)))]  # fmt: skip
    cal = calibration_rows("shelf", clean, faults) + calibration_rows("shelf noisy", noisy, faults)
    print("calibration: fault -> named; refined camera vs truth; raw MPJPE true / wrong / refined")
    for r in cal:
        print(f"  {r['scene']:<12} {r['fault']:<14} named {r['named']}; "
              f"{r.get('refined_rot_deg', float('nan')):.3f} deg, "
              f"{r.get('refined_centre_mm', float('nan')):.1f} mm; "
              f"{r['mpjpe_true']:.1f} / {r['mpjpe_wrong']:.1f} / "
              f"{r.get('mpjpe_refined', float('nan')):.1f} mm")  # fmt: skip
    T_down, T_yup = np.eye(4), np.eye(4)
    T_down[:3, :3] = Rotation.from_euler("x", 180, degrees=True).as_matrix()
    T_down[2, 3] = 1500
    T_yup[:3, :3] = Rotation.from_euler("x", -90, degrees=True).as_matrix()
    scenes = {
        "shelf": clean,
        "shelf z-down": transform_scene(clean, T_down, MODEL),
        "shelf y-up": transform_scene(clean, T_yup, MODEL),
        "pose2sim_balancing": load_scene(REPO / "sample_data" / "pose2sim_balancing"),
        "pose2sim_demo": load_scene(REPO / "sample_data" / "pose2sim_demo"),
    }
    floor = floor_rows(scenes)
    print("floor: up's angle to +z, floor height (method) -> after the fix")
    for r in floor:
        after = r.get("after_fix")
        tail = "" if after is None else (
            f" -> {after['angle_to_z_deg']:.2f} deg, {after['floor_height_mm']:.0f} mm")
        print(f"  {r['scene']:<20} {r['angle_to_z_deg']:7.2f} deg, {r['floor_height_mm']:7.0f} mm"
              f" ({r['method']}){tail}")  # fmt: skip
    med = {k: statistics.median(v) for k, v in TIMES.items() if v}
    print("time (median s): " + ", ".join(f"{k} {v:.2f}" for k, v in med.items()))
    if args.json:
        write_json(args.json, {"sync": sync, "calibration": cal, "floor": floor, "seconds": med})
    return 0


def _sweep(clean, noisy, json_path) -> int:
    rows = sweep_rows("shelf", clean) + sweep_rows("shelf noisy", noisy)
    print("sync sweep: delay -> found (error, confidence; largest |offset| of the others)")
    for r in rows:
        print(f"  {r['scene']:<12} cam {r['camera']} {r['delay']:+3d}: {r['found']:+7.3f} "
              f"({r['error']:.3f}, {r['confidence']:.2f}; "
              f"{r['max_false_offset']:.3f})")  # fmt: skip
    drift = [drift_row("shelf", clean), drift_row("shelf noisy", noisy)]
    print("drift: camera 1 in sync until frame 125, 3 frames late after; per 125-frame window")
    for d in drift:
        w = "; ".join(f"{a}-{b - 1}: {o:+.3f} (conf {c:.2f})" for a, b, o, c in d["windows"])
        print(f"  {d['scene']:<12} {w}")
    if json_path:
        write_json(json_path, {"sweep": rows, "drift": drift})
    return 0


if __name__ == "__main__":
    sys.exit(main())
