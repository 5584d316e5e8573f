"""Cost of the per-frame stages (association + triangulation) over cameras x people.

Scenes: ``mvviz synth``'s fast synthesis (no video) on a Panoptic-like dome of 5 m
radius (``dome:N:5000``, people in its 3 m capture circle), the shipped detector noise,
--frames frames per scene, for every cameras x people of the grid. Per scene, alternated
over --repeats runs: ``pipeline.run.run_frame`` on every frame with today's association
kernels (``pipeline.ray_affinity``) and with the ones they replaced (the reference:
``pipeline.associate.ray_distances_reference`` / ``average_linkage_reference``, patched
in); the median CPU time per frame (this process's own time: the machine is shared) and
wall time; association precision / recall (pairs of one frame, pipeline.metrics) and
triangulation MPJPE against the true keypoints (people matched per frame), both ways.

Then: the exponents of a least-squares fit ``cost ~ cameras^a people^b`` and
``cost ~ detections^c``, a table, and a log-log plot (docs/scale.png). Also the shipped
sample and its noisy twin (sample_data/shelf_synth, shelf_synth_noisy): frames/s and
accuracy both ways.

Usage:
    python bench/bench_scale.py [--cameras 4 8 16 31] [--people 1 5 10 20] [--frames 8]
        [--repeats 3] [--plot docs/scale.png] [--json FILE]
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pipeline.associate as associate  # noqa: E402
from bench.common import write_json  # noqa: E402
from pipeline import metrics  # noqa: E402
from pipeline.body_model import load_body_model  # noqa: E402
from pipeline.config import PipelineConfig  # noqa: E402
from pipeline.run import frame_rows, run_frame, select_2d  # noqa: E402
from pipeline.scene import Scene, load_scene  # noqa: E402
from pipeline.synth.rigs import dome_capture_radius, dome_rig  # noqa: E402
from pipeline.synth.scene_gen import SynthConfig, write_synth_scene  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DOME_MM = 5000.0


@contextlib.contextmanager
def reference_kernels():
    """Run association with the kernels as first written."""
    saved = associate.ray_distances, associate._average_linkage
    associate.ray_distances = associate.ray_distances_reference
    associate._average_linkage = associate.average_linkage_reference
    try:
        yield
    finally:
        associate.ray_distances, associate._average_linkage = saved


def run_all(scene: Scene, config: PipelineConfig, j2d, rows) -> tuple[list, float, float]:
    """Every frame's :func:`run_frame`: (results, CPU s per frame, wall s per frame)."""
    c, w = time.process_time(), time.perf_counter()
    out = [run_frame(scene, f, config, j2d, rows=rows[f]) for f in range(scene.num_frames)]
    n = max(scene.num_frames, 1)
    return out, (time.process_time() - c) / n, (time.perf_counter() - w) / n


def accuracy(scene: Scene, results: list) -> dict[str, float]:
    """Association P/R over the frames, triangulation MPJPE (mm) of matched people."""
    det = scene.detections
    cluster = np.full(len(det.frame), -1)
    for r in results:
        cluster[r.rows] = r.association.cluster
    scores = metrics.association_scores(cluster, det.gt_person_id, det.frame)
    gt = scene.gt
    errs = []
    for r in results:
        truth = gt.keypoints3d[gt.frame == r.frame]
        pred = r.triangulation.points
        for p, g in metrics.match_people(pred, truth):
            e = np.linalg.norm(pred[p] - truth[g], axis=-1)
            errs.append(e[np.isfinite(e)])
    e = np.concatenate(errs) if errs else np.zeros(0)
    return {
        "precision": scores["precision"],
        "recall": scores["recall"],
        "mpjpe_mm": float(e.mean()) if e.size else float("nan"),
    }


def measure(scene: Scene, repeats: int) -> dict:
    config = PipelineConfig()
    j2d = select_2d(scene, config, None)
    rows = frame_rows(scene, config)
    cost = {"new": [], "reference": []}
    res = {}
    for _ in range(repeats):
        for mode in ("reference", "new"):
            ctx = reference_kernels() if mode == "reference" else contextlib.nullcontext()
            with ctx:
                res[mode], cpu, wall = run_all(scene, config, j2d, rows)
            cost[mode].append((cpu, wall))
    out = {"detections_per_frame": float(len(scene.detections.frame) / scene.num_frames)}
    for mode, runs in cost.items():
        cpu, wall = np.median(np.array(runs), axis=0)
        out[mode] = {"cpu_s": float(cpu), "wall_s": float(wall), **accuracy(scene, res[mode])}
    return out


def fit_exponents(cams, people, dets, cost) -> dict[str, float]:
    """log cost = a log cameras + b log people + k, and log cost = c log detections + k."""
    y = np.log(cost)
    X = np.column_stack([np.log(cams), np.log(people), np.ones(len(y))])
    a, b, _ = np.linalg.lstsq(X, y, rcond=None)[0]
    c, _ = np.polyfit(np.log(dets), y, 1)
    return {"cameras": float(a), "people": float(b), "detections": float(c)}


def plot(grid: list[dict], path: Path, fits: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    for k, cams in enumerate(sorted({g["cameras"] for g in grid})):
        rows = sorted((g for g in grid if g["cameras"] == cams), key=lambda g: g["dets"])
        x = [g["dets"] for g in rows]
        colour = f"C{k}"
        ax.loglog(x, [g["new"]["cpu_s"] * 1000 for g in rows], "o-", color=colour,
                  label=f"{cams} cameras")  # fmt: skip
        ax.loglog(x, [g["reference"]["cpu_s"] * 1000 for g in rows], "x--", color=colour,
                  alpha=0.6)  # fmt: skip
    ax.axhline(4.0, color="grey", lw=0.8, ls=":")
    ax.text(ax.get_xlim()[0] * 1.1, 4.3, "250 frames/s", color="grey", fontsize=8)
    ax.set_xlabel("detections per frame")
    ax.set_ylabel("association + triangulation, CPU ms / frame")
    n, r = fits["new"], fits["reference"]
    ax.set_title(
        "solid: now (cost ~ dets^%.2f), dashed: before (~ dets^%.2f)" % (n["detections"], r["detections"]),
        fontsize=9,
    )  # fmt: skip
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cameras", type=int, nargs="+", default=[4, 8, 16, 31])
    ap.add_argument("--people", type=int, nargs="+", default=[1, 5, 10, 20])
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--plot", type=Path, default=REPO / "docs" / "scale.png")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    model = load_body_model()
    grid = []
    print(f"{'cams':>4s} {'people':>6s} {'dets':>6s} | {'ms/frame now':>12s} {'before':>8s} "
          f"{'ratio':>6s} | {'P/R now':>13s} {'P/R before':>13s} | {'MPJPE now/before':>16s}")  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="bench_scale.") as tmp:
        for cams in args.cameras:
            rig = dome_rig(cams, radius_mm=DOME_MM)
            for people in args.people:
                cfg = SynthConfig(
                    num_people=people, num_frames=args.frames, seed=cams * 100 + people,
                    render_video=False, area_radius_mm=dome_capture_radius(DOME_MM),
                    occlusion="proxy",
                )  # fmt: skip
                out = Path(tmp) / f"d{cams}_p{people}"
                write_synth_scene(out, rig, model, cfg, progress=False)
                m = measure(load_scene(out), args.repeats)
                g = {"cameras": cams, "people": people, "dets": m["detections_per_frame"], **m}
                grid.append(g)
                n, r = g["new"], g["reference"]
                print(f"{cams:4d} {people:6d} {g['dets']:6.1f} | {n['cpu_s'] * 1e3:12.2f} "
                      f"{r['cpu_s'] * 1e3:8.2f} {r['cpu_s'] / n['cpu_s']:6.1f} | "
                      f"{n['precision']:.4f}/{n['recall']:.4f} {r['precision']:.4f}/{r['recall']:.4f} | "
                      f"{n['mpjpe_mm']:7.2f}/{r['mpjpe_mm']:7.2f}", flush=True)  # fmt: skip
    arr = {k: np.array([g[k] for g in grid], float) for k in ("cameras", "people", "dets")}
    fits = {
        mode: fit_exponents(arr["cameras"], arr["people"], arr["dets"],
                            np.array([g[mode]["cpu_s"] for g in grid]))
        for mode in ("new", "reference")
    }  # fmt: skip
    for mode, f in fits.items():
        print(f"fit {mode:9s}: cost ~ cameras^{f['cameras']:.2f} people^{f['people']:.2f}; "
              f"~ detections^{f['detections']:.2f}")  # fmt: skip
    samples = {}
    for name in ("shelf_synth", "shelf_synth_noisy"):
        m = measure(load_scene(REPO / "sample_data" / name), args.repeats)
        samples[name] = m
        n, r = m["new"], m["reference"]
        print(f"{name}: {1 / n['cpu_s']:.0f} frames/s CPU now, {1 / r['cpu_s']:.0f} before "
              f"({1 / n['wall_s']:.0f} / {1 / r['wall_s']:.0f} wall); P/R "
              f"{n['precision']:.4f}/{n['recall']:.4f} vs {r['precision']:.4f}/{r['recall']:.4f}; "
              f"MPJPE {n['mpjpe_mm']:.2f} vs {r['mpjpe_mm']:.2f} mm")  # fmt: skip
    if args.plot:
        plot(grid, args.plot, fits)
        print(f"plot: {args.plot}")
    if args.json:
        write_json(args.json, {"grid": grid, "fits": fits, "samples": samples})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
