"""Benchmark the per-frame and sequence stages on the shipped sample scene.

Prints frames per second of each stage (2D restoration, association, triangulation,
tracking, Kalman filtering) and of stages 1-5 end to end, on sample_data/shelf_synth
(5 views x 4 people; COCO-17 keypoints, 24 SMPL joints for the restored source), as
the median of --repeats runs. In the same run, on the same clustered 2D input:

- aniposelib's CameraGroup.triangulate (time and MPJPE against the true keypoints),
  if aniposelib is installed (``pip install -e ".[bench]"``);
- the filterpy loop (bench/reference_kalman.py's kalman_filter_filterpy, one trajectory at a time)
  against the vectorised filter, on every track and joint of the run.

Usage:
    python bench/bench_pipeline.py [--scene DIR] [--repeats R] [--json FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_triangulate import anipose_group  # noqa: E402

from bench.common import markdown_table, publish, write_json  # noqa: E402
from bench.reference_kalman import kalman_filter_filterpy  # noqa: E402
from pipeline.association.associate import associate_frame  # noqa: E402
from pipeline.body.model import load_body_model  # noqa: E402
from pipeline.config import PipelineConfig  # noqa: E402
from pipeline.data.scene import load_scene  # noqa: E402
from pipeline.run.frames import frame_rows, restored_joints, run_frame, run_sequence  # noqa: E402
from pipeline.stages.kalman import kalman_filter  # noqa: E402
from pipeline.stages.triangulate import triangulate_people  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def median_time(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--scene", type=Path, default=REPO / "sample_data" / "shelf_synth")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--docs", action="store_true", help="write the documentation's section")
    args = ap.parse_args(argv)

    scene = load_scene(args.scene)
    model = load_body_model()
    config = PipelineConfig()
    F = scene.num_frames
    rows = frame_rows(scene)
    kp = scene.detections.keypoints
    figures: dict[str, dict] = {}

    t_restore, restored = median_time(lambda: restored_joints(scene, model), args.repeats)

    def associate_all(params=config.association):
        return [
            associate_frame(
                scene.rig, scene.detections.view[r], kp[r], params, joint_set=scene.joint_set
            )
            for r in rows
        ]

    t_assoc, assocs = median_time(associate_all, args.repeats)
    # The same without left/right resolution and duplicate merging (what they cost).
    plain = dataclasses.replace(config.association, resolve_flips=False, merge_distance_mm=0.0)
    t_assoc_plain, _ = median_time(lambda: associate_all(plain), args.repeats)

    # Triangulation input: per frame (people, views, joints, 3) from the clusters.
    V = len(scene.rig)
    inputs = []
    for r, a in zip(rows, assocs, strict=True):
        x = np.full((a.num_people, V, kp.shape[1], 3), np.nan)
        x[..., 2] = 0
        for p in range(a.num_people):
            for v in range(V):
                if a.members[p, v] >= 0:
                    x[p, v] = kp[r[a.members[p, v]]]
        inputs.append(x)
    tp = config.triangulation

    def triangulate_all():
        return [
            triangulate_people(
                scene.rig,
                x,
                min_confidence=tp.min_confidence,
                outlier_threshold_px=tp.outlier_threshold_px,
                min_views=tp.min_views,
            )
            for x in inputs
        ]

    t_tri, tris = median_time(triangulate_all, args.repeats)
    frames = [run_frame(scene, f, config, kp, rows=rows[f]) for f in range(F)]
    t_seq, seq = median_time(lambda: run_sequence(frames, F, config, scene.joint_set), args.repeats)
    meas = np.moveaxis(seq.tracks.joints, 1, 0)
    t_kal, _ = median_time(lambda: kalman_filter(meas, config.kalman), args.repeats)
    t_track = max(t_seq - t_kal, 1e-9)

    def end_to_end():
        r = restored_joints(scene, model)
        fr = [run_frame(scene, f, config, kp, rows=rows[f]) for f in range(F)]
        return r, run_sequence(fr, F, config, scene.joint_set)

    t_e2e, _ = median_time(end_to_end, args.repeats)
    for name, t in (
        ("restoration", t_restore),
        ("association", t_assoc),
        ("association without flips/merge", t_assoc_plain),
        ("triangulation", t_tri),
        ("tracking", t_track),
        ("kalman", t_kal),
        ("stages 1-5 end to end", t_e2e),
    ):
        figures[name] = {"seconds": t, "fps": F / t}

    # Accuracy of our triangulation vs aniposelib on the same clusters (vs true keypoints).
    det, gt = scene.detections, scene.gt
    ours_err, anip_err = [], []
    group = anipose_group(scene.rig)
    pts2d, truth, ours = [], [], []
    for f, (r, a, tri) in enumerate(zip(rows, assocs, tris, strict=True)):
        for p in range(a.num_people):
            members = a.members[p]
            ids = det.gt_person_id[r[members[members >= 0]]]
            if len(set(ids.tolist())) != 1 or ids[0] < 0:
                continue
            g = gt.keypoints3d[(gt.frame == f) & (gt.person_id == ids[0])][0]
            x = inputs[f][p]  # (V, J, 3)
            xy = np.where(x[..., 2:] >= tp.min_confidence, x[..., :2], np.nan)
            pts2d.append(xy)
            truth.append(g)
            ours.append(tri.points[p])
    pts2d = np.stack(pts2d, 1)  # (V, people, J, 2)
    truth, ours = np.stack(truth), np.stack(ours)
    out = {"stages": figures}
    if group is not None:
        flat = pts2d.reshape(V, -1, 2)
        group.triangulate(flat[:, :50], undistort=True, progress=False)  # warm-up (JIT)
        t_anip, anip = median_time(
            lambda: group.triangulate(flat, undistort=True, progress=False), args.repeats
        )
        anip = anip.reshape(truth.shape)
        both = np.isfinite(anip).all(-1) & np.isfinite(ours).all(-1)
        ours_err = np.linalg.norm(ours - truth, axis=-1)[both]
        anip_err = np.linalg.norm(anip - truth, axis=-1)[both]
        out["aniposelib"] = {
            "seconds": t_anip,
            "fps": F / t_anip,
            "mpjpe_mm": float(anip_err.mean()),
            "ours_mpjpe_mm": float(ours_err.mean()),
            "speed_ratio": t_anip / t_tri,
        }
    # filterpy loop vs vectorised, on every track x joint trajectory of the run.
    traj = meas.reshape(F, -1, 3)
    traj = traj[:, np.isfinite(traj).all(-1).any(0)]

    def filterpy_all():
        return [kalman_filter_filterpy(traj[:, i], config.kalman) for i in range(traj.shape[1])]

    t_fp, _ = median_time(filterpy_all, 1)
    t_vec, _ = median_time(lambda: kalman_filter(traj, config.kalman), args.repeats)
    out["kalman_filterpy_vs_vectorised"] = {
        "trajectories": int(traj.shape[1]),
        "filterpy_seconds": t_fp,
        "vectorised_seconds": t_vec,
        "speed_ratio": t_fp / t_vec,
    }

    print(f"scene {scene.name}: {F} frames, {V} views, {len(det)} detections")
    print(f"{'stage':<24} {'ms total':>9} {'frames/s':>10}")
    for name, v in figures.items():
        print(f"{name:<24} {1000 * v['seconds']:9.1f} {v['fps']:10.0f}")
    if "aniposelib" in out:
        a = out["aniposelib"]
        print(
            f"triangulation vs aniposelib: ours {F / t_tri:.0f} frames/s, MPJPE "
            f"{a['ours_mpjpe_mm']:.2f} mm; aniposelib {a['fps']:.0f} frames/s, MPJPE "
            f"{a['mpjpe_mm']:.2f} mm; speed ratio {a['speed_ratio']:.1f}x"
        )
    else:
        print("aniposelib not installed (pip install -e '.[bench]'): no baseline")
    k = out["kalman_filterpy_vs_vectorised"]
    fp_ms, vec_ms = 1000 * k["filterpy_seconds"], 1000 * k["vectorised_seconds"]
    print(
        f"kalman on {k['trajectories']} trajectories: filterpy loop {fp_ms:.0f} ms, "
        f"vectorised {vec_ms:.1f} ms, ratio {k['speed_ratio']:.0f}x"
    )
    if args.json:
        write_json(args.json, out)
    if args.docs:
        rows_md = [[name, f"{1000 * v['seconds']:.1f}", f"{v['fps']:.0f}"]
                   for name, v in figures.items()]  # fmt: skip
        body = (
            f"Stages 1-5 on `{args.scene.name}` ({F} frames, {V} views, {len(det)} "
            f"detections), median of {args.repeats} runs.\n\n"
            + markdown_table(["stage", "ms for the scene", "frames/s"], rows_md)
            + f"\n\nKalman filter on {k['trajectories']} trajectories: the vectorised filter "
            f"{vec_ms:.1f} ms against a filterpy loop's {fp_ms:.0f} ms: "
            f"**{k['speed_ratio']:.0f}x**."
        )
        if "aniposelib" in out:
            a = out["aniposelib"]
            body += (
                f" Triangulation against aniposelib on the same clusters: "
                f"{a['speed_ratio']:.1f}x its speed, MPJPE {a['ours_mpjpe_mm']:.1f} mm "
                f"against {a['mpjpe_mm']:.1f} mm."
            )
        publish("bench_pipeline", "Pipeline stages", body)
    return out


if __name__ == "__main__":
    main()
