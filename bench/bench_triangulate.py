"""Benchmark pipeline.triangulate.triangulate_people against aniposelib's CameraGroup.triangulate.

Scene: the real 5-camera Shelf rig (/work/shared/data/calibration/shelf_voxelpose.json),
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
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.cameras import CameraRig  # noqa: E402
from pipeline.importers.calibration import read_voxelpose_calibration  # noqa: E402
from pipeline.triangulate import triangulate_people  # noqa: E402

SHELF = Path(__file__).resolve().parents[2] / "shared/data/calibration/shelf_voxelpose.json"
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
    """Truth (F, P, J, 3) mm and keypoints (F, P, V, J, 3) distorted px + confidence."""
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
    uv = np.where(outlier[..., None], uv + shift, uv)
    uv[~inside] = np.nan
    conf = np.where(inside, rng.uniform(0.5, 1.0, inside.shape), 0.0)
    return truth, np.concatenate([uv, conf[..., None]], -1)


def timed(fn, repeats: int) -> tuple[float, object]:
    """Median seconds of ``repeats`` runs after one warm-up run, and the last result."""
    out = fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


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
            matrix=c.K, dist=c.dist, rvec=cv2.Rodrigues(c.R)[0].ravel(), tvec=c.t,
            size=(c.width, c.height), name=c.name,
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
    truth, kp = make_data(rig, F, args.seed)
    n_obs = np.isfinite(kp[..., 0]).sum()
    print(
        f"Shelf rig, {F} frames x {NUM_PEOPLE} people x {V} views x {NUM_JOINTS} joints; "
        f"{n_obs / kp[..., 0].size:.1%} of observations in view, "
        f"{OUTLIER_RATE:.0%} of those outliers, {NOISE_PX:g} px noise"
    )

    # Ours: one call per frame, and one call for all frames stacked as people.
    def ours_per_frame():
        return np.stack([triangulate_people(rig, kp[f]).points for f in range(F)])

    def ours_batched():
        stacked = kp.reshape(F * NUM_PEOPLE, V, NUM_JOINTS, 3)
        return triangulate_people(rig, stacked).points.reshape(truth.shape)

    results: dict = {"frames": F, "views": V, "people": NUM_PEOPLE, "joints": NUM_JOINTS}
    t_ours_f, ours = timed(ours_per_frame, args.repeats)
    t_ours_b, ours_b = timed(ours_batched, args.repeats)
    assert np.array_equal(np.isnan(ours), np.isnan(ours_b))

    group = anipose_group(rig)
    if group is not None:
        # (V, N, 2) per frame / for the whole sequence; NaN marks missing.
        pts = np.moveaxis(kp[..., :2], 2, 0).reshape(V, F, NUM_PEOPLE * NUM_JOINTS, 2)

        def anipose_per_frame():
            return np.stack([group.triangulate(pts[:, f], undistort=True) for f in range(F)])

        def anipose_batched():
            return group.triangulate(pts.reshape(V, -1, 2), undistort=True)

        t_ani_f, ani = timed(anipose_per_frame, args.repeats)
        t_ani_b, _ = timed(anipose_batched, args.repeats)
        ani = ani.reshape(truth.shape)
    both = np.isfinite(ours[..., 0]) & (group is None or np.isfinite(ani[..., 0]))
    results["joints_triangulated"] = int(both.sum())
    results["ours"] = {
        "fps_per_frame": F / t_ours_f,
        "fps_batched": F / t_ours_b,
        "mpjpe_mm": mpjpe(ours, truth, both),
    }
    rows = [("ours (triangulate_people)", results["ours"])]
    if group is not None:
        results["aniposelib"] = {
            "fps_per_frame": F / t_ani_f,
            "fps_batched": F / t_ani_b,
            "mpjpe_mm": mpjpe(ani, truth, both),
        }
        results["speed_ratio_per_frame"] = t_ani_f / t_ours_f
        results["speed_ratio_batched"] = t_ani_b / t_ours_b
        rows.append(("aniposelib CameraGroup.triangulate", results["aniposelib"]))

    print(f"{'':36s} {'frames/s per frame':>18s} {'frames/s batched':>17s} {'MPJPE mm':>9s}")
    for name, r in rows:
        print(
            f"{name:36s} {r['fps_per_frame']:18.0f} {r['fps_batched']:17.0f} "
            f"{r['mpjpe_mm']:9.2f}"
        )
    print(f"(MPJPE over the {both.sum()} joints both triangulate)")
    if group is not None:
        print(
            f"speed ratio ours / aniposelib: {results['speed_ratio_per_frame']:.1f}x per frame, "
            f"{results['speed_ratio_batched']:.1f}x batched"
        )
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")
    return results


if __name__ == "__main__":
    main()
