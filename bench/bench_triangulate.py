"""Benchmark pipeline.stages.triangulate.triangulate_people against aniposelib's
CameraGroup.triangulate.

Scene: the real 5-camera Shelf rig (sample_data/rigs/shelf_voxelpose.json, the same file as
/work/shared/data/calibration/shelf_voxelpose.json; no lens distortion in this rig),
4 people x 24 SMPL joints per frame, standing at random places on the floor that at least
3 cameras see, random heading, limbs jittered around a rest skeleton. 2D joints: the exact
projections plus 2 px Gaussian noise; joints outside an image are missing (NaN); 5% of the
remaining observations are outliers (moved 40-200 px in a random direction); confidence
uniform in [0.5, 1] for every observation (a detector does not know its outliers).

Both methods get the same 2D input. aniposelib's CameraGroup is built from the same
cameras (matrix=K, dist, rvec=Rodrigues(R), tvec=t, size) and called with undistort=True
on the (V, N, 2) array, NaN for missing (it has no confidences and no outlier rejection:
it is the plain DLT of every view). Two ways to call each:

  per frame   one call per frame (what an online pipeline does)
  batched     one call for the whole sequence (frames stacked as people / points)

Prints frames/s (median of --repeats timed runs, after one warm-up run that also pays
aniposelib's JIT compilation), the MPJPE (mean 3D error, mm, over the joints both methods
triangulate) against the known truth, and the speed ratio. If aniposelib is not
installed, says so and reports our own numbers only.

Usage:
    python bench/bench_triangulate.py [--frames N] [--repeats R] [--seed S] [--json FILE]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import write_json  # noqa: E402
from pipeline.data.cameras import CameraRig  # noqa: E402
from pipeline.importers.calibration import read_voxelpose_calibration  # noqa: E402
from pipeline.stages.triangulate import triangulate_people  # noqa: E402

# The real Shelf calibration; the repository's copy is identical to
# /work/shared/data/calibration/shelf_voxelpose.json.
SHELF = Path(__file__).resolve().parents[1] / "sample_data/rigs/shelf_voxelpose.json"
NUM_PEOPLE, NUM_JOINTS = 4, 24
NOISE_PX, OUTLIER_RATE, OUTLIER_PX = 2.0, 0.05, (40.0, 200.0)

# SMPL-24 rest skeleton, mm: x to the person's left, y forward, z up (feet on the floor).
REST_JOINTS = np.array([
    [0, 0, 950], [90, 0, 870], [-90, 0, 870], [0, -10, 1060], [100, 10, 500],
    [-100, 10, 500], [0, -10, 1190], [105, -20, 90], [-105, -20, 90], [0, -10, 1240],
    [110, 100, 30], [-110, 100, 30], [0, 0, 1470], [80, 0, 1390], [-80, 0, 1390],
    [0, 20, 1580], [180, 0, 1400], [-180, 0, 1400], [200, 0, 1140], [-200, 0, 1140],
    [210, 30, 900], [-210, 30, 900], [215, 40, 820], [-215, 40, 820],
], float)  # fmt: skip
# Per-joint jitter, mm: hands and feet move most.
JITTER = np.array([
    20, 30, 30, 20, 60, 60, 20, 90, 90, 20, 100, 100, 30, 30, 30, 40, 40, 40, 120, 120,
    180, 180, 200, 200,
], float)  # fmt: skip


def floor_area(rig: CameraRig, min_views: int = 3) -> np.ndarray:
    """(K, 2) floor points where a standing person (feet and head) is inside >= min_views images."""
    lo, hi = rig.centers[:, :2].min(0), rig.centers[:, :2].max(0)
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0], 100.0), np.arange(lo[1], hi[1], 100.0))
    ground = np.stack([gx.ravel(), gy.ravel()], -1)
    count = np.zeros(len(ground), int)
    for cam in rig:
        ok = np.ones(len(ground), bool)
        for h in (0.0, 1700.0):
            uv = cam.project(np.column_stack([ground, np.full(len(ground), h)]))
            ok &= np.isfinite(uv).all(1) & (uv > 20).all(1)
            ok &= (uv[:, 0] < cam.width - 20) & (uv[:, 1] < cam.height - 20)
        count += ok
    return ground[count >= min_views]


def make_data(rig: CameraRig, frames: int, seed: int):
    """Truth (F, P, J, 3) mm; keypoints (F, P, V, J, 3) distorted px + confidence, with
    outliers and without (the same noise otherwise)."""
    rng = np.random.default_rng(seed)
    area = floor_area(rig)
    truth = np.empty((frames, NUM_PEOPLE, NUM_JOINTS, 3))
    for f in range(frames):
        spots: list[np.ndarray] = []
        while len(spots) < NUM_PEOPLE:  # people at least 700 mm apart
            s = area[rng.integers(len(area))]
            if all(np.linalg.norm(s - o) > 700 for o in spots):
                spots.append(s)
        for p, spot in enumerate(spots):
            a = rng.uniform(0, 2 * np.pi)
            Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
            body = REST_JOINTS + rng.normal(size=REST_JOINTS.shape) * JITTER[:, None]
            truth[f, p] = body @ Rz.T + np.array([spot[0], spot[1], 0.0])
    uv = np.moveaxis(rig.project(truth), 0, 2)  # (F, P, V, J, 2)
    size = np.array([[c.width, c.height] for c in rig])[:, None]  # (V, 1, 2)
    inside = np.isfinite(uv).all(-1) & (uv >= 0).all(-1) & (uv < size).all(-1)
    uv = uv + rng.normal(0, NOISE_PX, uv.shape)
    outlier = inside & (rng.uniform(size=inside.shape) < OUTLIER_RATE)
    angle = rng.uniform(0, 2 * np.pi, outlier.shape)
    radius = rng.uniform(*OUTLIER_PX, outlier.shape)
    shift = np.stack([np.cos(angle), np.sin(angle)], -1) * radius[..., None]
    uv[~inside] = np.nan
    conf = np.where(inside, rng.uniform(0.5, 1.0, inside.shape), 0.0)[..., None]
    clean = np.concatenate([uv, conf], -1)
    return truth, np.concatenate([np.where(outlier[..., None], uv + shift, uv), conf], -1), clean


def timed(fns: dict, repeats: int) -> tuple[dict, dict]:
    """Median seconds of ``repeats`` runs of each function, after one warm-up run each, and
    their results. The functions take turns, so that a change of machine load hits all."""
    results = {name: fn() for name, fn in fns.items()}
    times: dict = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            results[name] = fn()
            times[name].append(time.perf_counter() - t0)
    return {name: float(np.median(t)) for name, t in times.items()}, results


def mpjpe(estimate: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    return float(np.linalg.norm(estimate - truth, axis=-1)[mask].mean())


def anipose_group(rig: CameraRig):
    """aniposelib CameraGroup of the same cameras, or None if aniposelib is missing."""
    try:
        from aniposelib.cameras import Camera as AniposeCamera
        from aniposelib.cameras import CameraGroup
    except ImportError as exc:  # optional: the benchmark still reports our own numbers
        print(f"aniposelib is NOT available ({exc}); reporting our own numbers only")
        return None
    cams = [
        AniposeCamera(
            matrix=c.K,
            dist=c.dist,
            rvec=cv2.Rodrigues(c.R)[0].ravel(),
            tvec=c.t,
            size=(c.width, c.height),
            name=c.name,
        )  # fmt: skip
        for c in rig
    ]
    return CameraGroup(cams)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--frames", type=int, default=250, help="frames of synthetic data (250)")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per figure (5)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, help="also write the figures to this file")
    args = ap.parse_args(argv)

    rig = read_voxelpose_calibration(SHELF)
    F, V = args.frames, len(rig)
    truth, kp, kp_clean = make_data(rig, F, args.seed)
    n_obs = np.isfinite(kp[..., 0]).sum()
    print(
        f"Shelf rig, {F} frames x {NUM_PEOPLE} people x {V} views x {NUM_JOINTS} joints; "
        f"{n_obs / kp[..., 0].size:.1%} of observations in view, "
        f"{OUTLIER_RATE:.0%} of those outliers, {NOISE_PX:g} px noise"
    )

    # Ours: one call per frame, and one call for all frames stacked as people.
    def ours_per_frame(keypoints=kp):
        return np.stack([triangulate_people(rig, keypoints[f]).points for f in range(F)])

    def ours_batched(keypoints=kp):
        stacked = keypoints.reshape(F * NUM_PEOPLE, V, NUM_JOINTS, 3)
        return triangulate_people(rig, stacked).points.reshape(truth.shape)

    fns = {"ours_per_frame": ours_per_frame, "ours_batched": ours_batched}
    group = anipose_group(rig)
    if group is not None:

        def anipose_points(keypoints):  # (V, F, N, 2); NaN marks missing
            return np.moveaxis(keypoints[..., :2], 2, 0).reshape(V, F, -1, 2)

        def anipose_per_frame(keypoints=kp):
            pts = anipose_points(keypoints)
            out = [group.triangulate(pts[:, f], undistort=True) for f in range(F)]
            return np.stack(out).reshape(truth.shape)

        def anipose_batched(keypoints=kp):
            pts = anipose_points(keypoints).reshape(V, -1, 2)
            return group.triangulate(pts, undistort=True).reshape(truth.shape)

        fns |= {"anipose_per_frame": anipose_per_frame, "anipose_batched": anipose_batched}
    seconds, out = timed(fns, args.repeats)
    assert np.allclose(out["ours_per_frame"], out["ours_batched"], atol=1e-6, equal_nan=True)

    # MPJPE over the joints that every method triangulates, with and without outliers.
    estimates = {"ours": (out["ours_per_frame"], ours_per_frame(kp_clean))}
    if group is not None:
        estimates["aniposelib"] = (out["anipose_per_frame"], anipose_per_frame(kp_clean))
    both = np.ones(truth.shape[:-1], bool)
    for est in estimates.values():
        both &= np.isfinite(est[0][..., 0]) & np.isfinite(est[1][..., 0])
    results: dict = {"frames": F, "views": V, "people": NUM_PEOPLE, "joints": NUM_JOINTS}
    results["joints_evaluated"] = int(both.sum())
    names = {"ours": "ours (triangulate_people)", "aniposelib": "aniposelib triangulate"}
    prefix = {"ours": "ours", "aniposelib": "anipose"}
    print(
        f"{'':28s} {'frames/s per frame':>18s} {'frames/s batched':>17s} {'MPJPE mm':>9s}"
        f" {'MPJPE, no outliers':>19s}"
    )
    for key, (with_outliers, without) in estimates.items():
        r = results[key] = {
            "fps_per_frame": F / seconds[f"{prefix[key]}_per_frame"],
            "fps_batched": F / seconds[f"{prefix[key]}_batched"],
            "mpjpe_mm": mpjpe(with_outliers, truth, both),
            "mpjpe_no_outliers_mm": mpjpe(without, truth, both),
        }
        print(
            f"{names[key]:28s} {r['fps_per_frame']:18.0f} {r['fps_batched']:17.0f} "
            f"{r['mpjpe_mm']:9.2f} {r['mpjpe_no_outliers_mm']:19.2f}"
        )
    print(f"(MPJPE over the {both.sum()} joints both triangulate; median of {args.repeats} runs)")
    if group is not None:
        results["speed_ratio_per_frame"] = seconds["anipose_per_frame"] / seconds["ours_per_frame"]
        results["speed_ratio_batched"] = seconds["anipose_batched"] / seconds["ours_batched"]
        print(
            f"speed ratio ours / aniposelib: {results['speed_ratio_per_frame']:.1f}x per frame, "
            f"{results['speed_ratio_batched']:.1f}x batched"
        )
    load = os.getloadavg()[0]
    print(f"(wall clock on {os.cpu_count()} CPUs, load average {load:.1f} during the run)")
    results["load_average"] = load
    if args.json:
        write_json(args.json, results)
    return results


if __name__ == "__main__":
    main()
