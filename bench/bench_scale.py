"""Cost of the per-frame stages (association, triangulation) over cameras x people.

Scenes: ``mvviz synth``'s fast synthesis (no video) on a Panoptic-like dome of 5 m
radius (``dome:N:5000``, people in its 3 m capture circle), the shipped detector noise,
--frames frames per scene, for every cameras x people of the grid (kept under --cache
and reused). Per scene, alternated over --repeats runs: ``pipeline.run.frames.run_frame`` on
every frame with the product's association (``pipeline.association.affinity.screened_distances``: a
part-ray screen, then the per-joint kernel on the pairs it keeps, in one compiled pass,
``pipeline.association.fused``, where a frame has ``COMPILED_MIN_DETECTIONS`` detections), with
the NumPy screen and kernel on every frame ("numpy": by cache-sized blocks,
``pipeline.association.pairs``), with the screen and kernel before the blocks
("unblocked": ``screen_distances_unblocked``, ``pair_ray_distances_unchunked``), with
the association before the screen (``bench.reference_association.dense_frame_distances``: every
pair, patched in), and
with --reference also the kernels as first written (``ray_distances_reference`` /
``average_linkage_reference``). Reported: the median CPU time per frame of association
and of triangulation (this process's own time: the machine is shared), association
precision / recall (pairs of one frame, pipeline.evaluation.metrics) and triangulation MPJPE
against the true keypoints (people matched per frame), every way.

Then: the exponents of a least-squares fit ``cost ~ cameras^a people^b`` and
``cost ~ detections^c``, a table (--markdown writes it for the README), and a log-log
plot (--plot). Also the shipped sample and its noisy twin (sample_data/shelf_synth,
shelf_synth_noisy): frames/s end to end (association + triangulation) and accuracy.

Usage:
    python bench/bench_scale.py [--cameras 4 8 16 31] [--people 1 5 10 20] [--frames 8]
        [--repeats 3] [--reference] [--cache DIR] [--plot docs/scale.png]
        [--markdown FILE] [--json FILE] [--from-json FILE: table and plot of a run]
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pipeline.association.affinity as ray_affinity  # noqa: E402
import pipeline.association.associate as associate  # noqa: E402
import pipeline.run.frames as run  # noqa: E402
from bench import reference_association as reference  # noqa: E402
from bench.common import write_json  # noqa: E402
from pipeline.config import PipelineConfig  # noqa: E402
from pipeline.data.scene import Scene, load_scene  # noqa: E402
from pipeline.evaluation import metrics  # noqa: E402
from pipeline.run.frames import frame_rows, run_frame, select_2d  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DOME_MM = 5000.0
STAGES = ("associate_frame", "triangulate_people")  # pipeline.run.frames's names, timed apart


@contextlib.contextmanager
def kernels(mode: str):
    """Association as shipped ("new": the compiled screen and kernel where a frame has
    ``COMPILED_MIN_DETECTIONS`` detections), with the NumPy screen and kernel on every
    frame ("numpy": the NumPy path without the compiled pass), with those before they went
    by cache-sized blocks ("unblocked": ``reference.screen_distances_unblocked``,
    ``pair_ray_distances_unchunked``), with every pair's distance ("dense", the kernels
    before the screen) or with the kernels as first written ("reference"); the kernels
    of the last three are bench/reference_association.py's."""
    saved = associate._frame_distances, reference.ray_distances, associate._average_linkage
    saved_screen = ray_affinity._pair_kernel, ray_affinity._screen
    saved_min = ray_affinity.COMPILED_MIN_DETECTIONS
    if mode != "new":  # every other mode is a NumPy one
        ray_affinity.COMPILED_MIN_DETECTIONS = sys.maxsize
    if mode == "unblocked":
        ray_affinity._pair_kernel = reference.pair_ray_distances_unchunked
        ray_affinity._screen = reference.screen_distances_unblocked
    if mode in ("dense", "reference"):
        associate._frame_distances = reference.dense_frame_distances
    if mode == "reference":
        reference.ray_distances = reference.ray_distances_reference
        associate._average_linkage = reference.average_linkage_reference
    try:
        yield
    finally:
        associate._frame_distances, reference.ray_distances, associate._average_linkage = saved
        ray_affinity._pair_kernel, ray_affinity._screen = saved_screen
        ray_affinity.COMPILED_MIN_DETECTIONS = saved_min


@contextlib.contextmanager
def stage_clock():
    """CPU seconds spent in each of :data:`STAGES` (pipeline.run.frames's functions wrapped)."""
    spent: dict[str, float] = collections.defaultdict(float)
    saved = {name: getattr(run, name) for name in STAGES}

    def timed(name, fn):
        def call(*args, **kwargs):
            c = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[name] += time.process_time() - c

        return call

    for name, fn in saved.items():
        setattr(run, name, timed(name, fn))
    try:
        yield spent
    finally:
        for name, fn in saved.items():
            setattr(run, name, fn)


def run_all(scene: Scene, config: PipelineConfig, j2d, rows) -> tuple[list, dict[str, float]]:
    """Every frame's :func:`run_frame`: (results, CPU s per frame of each stage and all)."""
    n = max(scene.num_frames, 1)
    with stage_clock() as spent:
        c = time.process_time()
        out = [run_frame(scene, f, config, j2d, rows=rows[f]) for f in range(scene.num_frames)]
        total = time.process_time() - c
    return out, {
        "assoc_s": spent["associate_frame"] / n,
        "tri_s": spent["triangulate_people"] / n,
        "frame_s": total / n,
    }


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


def measure(scene: Scene, repeats: int, modes: tuple[str, ...]) -> dict:
    """Median CPU s per frame of each stage and accuracy, per mode, alternated."""
    config = PipelineConfig()
    j2d = select_2d(scene, config, None)
    rows = frame_rows(scene, config)
    cost: dict[str, list] = {m: [] for m in modes}
    res = {}
    for _ in range(repeats):
        for mode in modes:
            with kernels(mode):
                res[mode], spent = run_all(scene, config, j2d, rows)
            cost[mode].append(spent)
    out = {"detections_per_frame": float(len(scene.detections.frame) / scene.num_frames)}
    for mode, runs in cost.items():
        med = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
        out[mode] = {**med, **accuracy(scene, res[mode])}
    return out


def dome_scene(cache: Path, cams: int, people: int, frames: int) -> Scene:
    """The grid's scene, synthesised once into ``cache``."""
    out = cache / f"dome{cams}_p{people}_f{frames}"
    if not (out / "scene.json").exists():
        from pipeline.body.model import load_body_model
        from pipeline.synth.rigs import dome_capture_radius, dome_rig
        from pipeline.synth.scene_gen import SynthConfig, write_synth_scene

        cfg = SynthConfig(
            num_people=people, num_frames=frames, seed=cams * 100 + people,
            render_video=False, area_radius_mm=dome_capture_radius(DOME_MM), occlusion="proxy",
        )  # fmt: skip
        rig = dome_rig(cams, radius_mm=DOME_MM)
        write_synth_scene(out, rig, load_body_model(), cfg, progress=False)
    return load_scene(out)


def fit_exponents(cams, people, dets, cost) -> dict[str, float]:
    """log cost = a log cameras + b log people + k, and log cost = c log detections + k."""
    y = np.log(cost)
    X = np.column_stack([np.log(cams), np.log(people), np.ones(len(y))])
    a, b, _ = np.linalg.lstsq(X, y, rcond=None)[0]
    c, _ = np.polyfit(np.log(dets), y, 1)
    return {"cameras": float(a), "people": float(b), "detections": float(c)}


def all_fits(grid: list[dict], modes: tuple[str, ...]) -> dict[str, dict[str, float]]:
    """Exponents of association per mode and of the triangulation."""
    arr = [np.array([g[k] for g in grid], float) for k in ("cameras", "people", "dets")]
    fits = {f"assoc_{m}": fit_exponents(*arr, np.array([g[m]["assoc_s"] for g in grid]))
            for m in modes}  # fmt: skip
    fits["tri_new"] = fit_exponents(*arr, np.array([g["new"]["tri_s"] for g in grid]))
    big = [g for g in grid if g["dets"] >= 100]  # past the fixed per-call costs
    if len(big) >= 4:
        for m in modes:
            fits[f"assoc_{m}_100"] = fit_exponents(
                *[np.array([g[k] for g in big], float) for k in ("cameras", "people", "dets")],
                np.array([g[m]["assoc_s"] for g in big]),
            )
    return fits


def plot(grid: list[dict], path: Path, fits: dict) -> None:
    """Association (left) and triangulation (right), CPU ms per frame against detections
    per frame, log-log, one colour per camera count."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4.6), dpi=110)
    for k, cams in enumerate(sorted({g["cameras"] for g in grid})):
        rows = sorted((g for g in grid if g["cameras"] == cams), key=lambda g: g["dets"])
        x, colour = [g["dets"] for g in rows], f"C{k}"
        ms = {(m, k): [g[m][k] * 1000 for g in rows] for m in ("new", "dense") for k in
              ("assoc_s", "tri_s")}  # fmt: skip
        label = f"{cams} cameras"
        ax.loglog(x, ms["new", "assoc_s"], "o-", color=colour, label=label)
        ax.loglog(x, ms["dense", "assoc_s"], "x--", color=colour, alpha=0.6)
        ax2.loglog(x, ms["new", "tri_s"], "o-", color=colour, label=label)
    for a, limit, text in ((ax, 4.0, "250 frames/s"), (ax, 10.0, "100 frames/s")):
        a.axhline(limit, color="grey", lw=0.8, ls=":")
        a.text(2, limit * 1.08, text, color="grey", fontsize=8)
    n, d, t = fits["assoc_new"], fits["assoc_dense"], fits["tri_new"]
    tail = lambda key: (  # noqa: E731
        f", >= 100 dets: ^{fits[key]['detections']:.2f}" if key in fits else ""
    )
    ax.set_title(
        f"association (solid: now ~ dets^{n['detections']:.2f}{tail('assoc_new_100')};"
        f"\ndashed: every pair ~ dets^{d['detections']:.2f}{tail('assoc_dense_100')})",
        fontsize=9,
    )
    ax2.set_title(
        f"triangulation (~ dets^{t['detections']:.2f} = cams^{t['cameras']:.2f}"
        f" people^{t['people']:.2f})",
        fontsize=9,
    )
    for a in (ax, ax2):
        a.set_xlabel("detections per frame")
        a.set_ylabel("CPU ms / frame")
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


def table(grid: list[dict]) -> list[str]:
    """The grid as a Markdown table: frames/s (CPU) per stage, accuracy."""
    out = [
        "| cameras | people | detections / frame | association frames/s (NumPy; every "
        "pair) | speed-up vs NumPy (vs every pair) | triangulation frames/s | association P / R | "
        "MPJPE mm (every pair) |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for g in grid:
        n, d = g["new"], g["dense"]
        u = g.get("numpy", n)  # runs before this mode: none
        out.append(
            f"| {g['cameras']} | {g['people']} | {g['dets']:.0f} | {1 / n['assoc_s']:,.0f} "
            f"({1 / u['assoc_s']:,.0f}; {1 / d['assoc_s']:,.0f}) | "
            f"{u['assoc_s'] / n['assoc_s']:.2f}x ({d['assoc_s'] / n['assoc_s']:.1f}x) | "
            f"{1 / n['tri_s']:,.0f} | {n['precision']:.4f} / {n['recall']:.4f} | "
            f"{n['mpjpe_mm']:.2f} ({d['mpjpe_mm']:.2f}) |"
        )
    return out


def report(name: str, m: dict, modes: tuple[str, ...]) -> str:
    """One line per scene: frames/s and accuracy of every mode."""
    parts = []
    for mode in modes:
        r = m[mode]
        parts.append(
            f"{mode}: assoc {1 / r['assoc_s']:7.0f}/s tri {1 / r['tri_s']:6.0f}/s "
            f"end to end {1 / r['frame_s']:6.0f}/s P/R {r['precision']:.4f}/{r['recall']:.4f} "
            f"MPJPE {r['mpjpe_mm']:.2f}"
        )
    return f"{name} ({m['detections_per_frame']:.0f} dets/frame) | " + " | ".join(parts)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cameras", type=int, nargs="+", default=[4, 8, 16, 31])
    ap.add_argument("--people", type=int, nargs="+", default=[1, 5, 10, 20])
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--reference", action="store_true", help="also the first kernels")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/bench_scale_scenes"))
    optional_path = lambda s: Path(s) if s else None  # noqa: E731  ("" = no plot)
    ap.add_argument("--plot", type=optional_path, default=REPO / "docs" / "scale.png")
    ap.add_argument("--markdown", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--from-json", type=Path, default=None, help="table and plot of a run")
    args = ap.parse_args(argv)
    modes = ("new", "numpy", "unblocked", "dense") + (("reference",) if args.reference else ())
    if args.from_json:
        saved = json.loads(args.from_json.read_text())
        modes = tuple(m for m in modes if m in saved["grid"][0])  # older runs lack some
        return finish(args, saved["grid"], all_fits(saved["grid"], modes), saved["samples"])
    print(f"load average at start: {os.getloadavg()}", flush=True)
    grid = []
    for cams in args.cameras:
        for people in args.people:
            m = measure(dome_scene(args.cache, cams, people, args.frames), args.repeats, modes)
            grid.append({"cameras": cams, "people": people, "dets": m["detections_per_frame"], **m})
            print(report(f"dome:{cams} x {people}", m, modes), flush=True)
    samples = {}
    for name in ("shelf_synth", "shelf_synth_noisy"):
        samples[name] = measure(load_scene(REPO / "sample_data" / name), args.repeats, modes)
        print(report(name, samples[name], modes), flush=True)
    print(f"load average at end: {os.getloadavg()}")
    return finish(args, grid, all_fits(grid, modes), samples)


def finish(args: argparse.Namespace, grid: list[dict], fits: dict, samples: dict) -> int:
    """The fits, the table, the plot and the JSON of a run."""
    for name, f in fits.items():
        print(f"fit {name:18s}: cost ~ cameras^{f['cameras']:.2f} people^{f['people']:.2f}; "
              f"~ detections^{f['detections']:.2f}")  # fmt: skip
    lines = table(grid)
    print("\n".join(lines))
    if args.markdown:
        args.markdown.write_text("\n".join(lines) + "\n")
    if args.plot:
        plot(grid, args.plot, fits)
        print(f"plot: {args.plot}")
    if args.json:
        write_json(args.json, {"grid": grid, "fits": fits, "samples": samples})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
