"""Peak memory of the pipeline's stages on long scenes, against the number of frames.

Long scenes are made by tiling a short scene in time, not by synthesis (a 31-camera x
20-person dome synthesises at ~3 frames/s): the base scene's detection rows are looped
forward and backward in time (:func:`tiled_scene`; keypoints, views and frames only: the
monocular SMPL predictions are left out, the configured source is the 2D keypoints; no
ground truth). People reverse their motion at every seam but do not jump, so the tracks
run through the whole scene as they would in a long recording.
Base scenes: the shipped sample (5 cameras x 4 people, 250 frames) and, with --dome, a
``mvviz synth`` dome (31 cameras x 20 people by default, --dome-frames frames,
synthesised once into --cache).

Each measurement runs in a process of its own (peaks do not mix) and reports, by a thread
sampling /proc/self/statm every 5 ms, the RSS before the stages (Python, numpy, the
tiled scene and its 2D joints) and the peak during each stage; also ru_maxrss and CPU
seconds. Modes, measured alternately per frame count:

* ``keep``: ``pack_run(run_frames(...))``, the stages before the chunked ones (every
  frame's result kept until tracking and packing);
* ``chunked``: :func:`pipeline.run.chunked.run_stages_chunked` (each frame packed at
  once), same results;
* ``lean``: the same without the affinity edges (``keep_edges=False``);
* ``fit``: ``lean``, then the chunked SMPL fit of the RTS tracks
  (:func:`pipeline.fit.chunks.fit_in_chunks`, step I);
* ``stream``: the tiled scene written once as a scene whose detections are a directory of
  ``.npy`` columns (:func:`write_tiled_scene`), read lazily by ``load_scene``, and
  :func:`pipeline.run.streamed.run_stages_streamed` writing the results directory as
  it goes (no edges; "before" is then the peak while the scene loads);
* ``streamedges``: the same with the affinity edges (what ``mvviz run`` keeps);
* ``streamfit``: ``stream``, then the chunked SMPL fit as in ``fit``.

Growth per frame is the least-squares slope of peak RSS over the frame counts measured;
nothing is extrapolated.

Usage:
    python bench/bench_memory.py [--frames 1000 2500 5000 10000] [--modes keep chunked lean
        stream streamedges streamfit]
        [--dome] [--dome-frames 10] [--cameras 31] [--people 20] [--json FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

REPO = Path(__file__).resolve().parents[1]
PAGE = os.sysconf("SC_PAGE_SIZE")
MB = 1024.0 * 1024.0


def rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * PAGE / MB


class PeakSampler:
    """Peak RSS (MB) per named stage, sampled every ``period`` seconds by a thread."""

    def __init__(self, period: float = 0.005):
        self.period, self.peaks, self._stage = period, {}, None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            if self._stage is not None:
                self.peaks[self._stage] = max(self.peaks.get(self._stage, 0.0), rss_mb())

    def stage(self, name: str) -> None:
        self._stage = name
        self.peaks[name] = rss_mb()

    def stop(self) -> dict[str, float]:
        self._stop.set()
        self._thread.join()
        return self.peaks


def tiled_scene(base, num_frames: int):
    """``base`` looped forward and backward in time (a palindrome: frames 0..F-1, then
    F-1..0, ...) to ``num_frames`` frames, keypoint rows only. Backward copies keep every
    person where the last copy left them, so tracks do not break at the seams (a plain
    repeat makes a new set of tracks per copy: tracks x frames then grows as frames^2)."""
    from pipeline.data.scene import Detections

    det, f0 = base.detections, base.num_frames
    reps = -(-num_frames // f0)
    frame = np.concatenate(
        [k * f0 + (det.frame if k % 2 == 0 else f0 - 1 - det.frame) for k in range(reps)]
    )
    keep = frame < num_frames
    tiled = Detections(
        frame=frame[keep],
        view=np.tile(det.view, reps)[keep],
        keypoints=np.concatenate([det.keypoints] * reps)[keep],
    )
    return dataclasses.replace(base, detections=tiled, num_frames=num_frames, gt=None)


def write_tiled_scene(base_dir: Path, num_frames: int, out: Path) -> Path:
    """:func:`tiled_scene` of ``base_dir`` written as a scene whose detections are a
    directory of ``.npy`` columns (read lazily by ``load_scene``), the keypoints copied
    one tile at a time: the scene a ``stream`` run reads is never whole in any memory."""
    from pipeline.core.npy_stream import open_npy_for_writing, release_pages
    from pipeline.data.scene import load_scene

    if (out / "scene.json").exists():
        return out
    base = load_scene(base_dir)
    det, f0 = base.detections, base.num_frames
    reps = -(-num_frames // f0)
    tmp = out.with_name(out.name + ".tmp")
    if tmp.exists():
        import shutil

        shutil.rmtree(tmp)
    (tmp / "detections").mkdir(parents=True)
    frames = [k * f0 + (det.frame if k % 2 == 0 else f0 - 1 - det.frame) for k in range(reps)]
    keep = [f < num_frames for f in frames]
    n = int(sum(k.sum() for k in keep))
    np.save(
        tmp / "detections" / "frame.npy",
        np.concatenate([f[k] for f, k in zip(frames, keep, strict=True)]),
    )
    np.save(tmp / "detections" / "view.npy", np.concatenate([det.view[k] for k in keep]))
    kp = open_npy_for_writing(tmp / "detections" / "keypoints.npy", np.float64,
                              (n, *det.keypoints.shape[1:]))  # fmt: skip
    i = 0
    for k in keep:
        kp[i : i + k.sum()] = det.keypoints[k]
        i += int(k.sum())
        release_pages(kp)
    kp.flush()
    del kp
    meta = json.loads((base_dir / "scene.json").read_text())
    meta.update(num_frames=num_frames, detections="detections", gt=None, videos=None)
    meta.pop("references", None)
    (tmp / "scene.json").write_text(json.dumps(meta, indent=1))
    (tmp / "cameras.json").write_bytes(
        (base_dir / meta.get("cameras", "cameras.json")).read_bytes()
    )
    tmp.rename(out)
    return out


def child_streamed(scene_dir: str, mode: str, chunk: int) -> dict:
    """A ``stream`` / ``streamfit`` / ``streamedges`` measurement: the lazily read scene,
    the stages streamed into a results directory (``streamedges``: with the affinity
    edges, as ``mvviz run`` keeps them), then (``streamfit``) the chunked SMPL fit."""
    import tempfile

    from pipeline.config import PipelineConfig
    from pipeline.data.scene import load_scene
    from pipeline.run.frames import select_2d
    from pipeline.run.streamed import STREAMED_CHUNK_FRAMES, run_stages_streamed

    config = PipelineConfig()
    model = None
    if mode == "streamfit":
        from pipeline.body.model import load_body_model

        model = load_body_model()
    sampler = PeakSampler()
    sampler.stage("before")
    scene = load_scene(scene_dir)
    j2d = select_2d(scene, config, None)
    t0 = time.process_time()
    sampler.stage("stages")
    with tempfile.TemporaryDirectory(dir=Path(scene_dir).parent) as tmp:
        res = run_stages_streamed(
            scene, config, j2d, Path(tmp) / "results", restored=None,
            chunk_frames=chunk or STREAMED_CHUNK_FRAMES, keep_edges=mode == "streamedges",
            progress=False,
        )  # fmt: skip
        t_stages = time.process_time() - t0
        fit = _fit(sampler, model, res)
        out = {
            "frames": scene.num_frames, "mode": mode, "rows": len(scene.detections),
            "person_frames_found": len(res.person_frame), "edges": len(res.edge_a),
            "tracks": res.num_tracks, "rss_before_mb": sampler.peaks["before"],
            "stages_cpu_s": t_stages, **fit,
        }  # fmt: skip
        del res
    peaks = sampler.stop()
    return {
        **out, "peak_stages_mb": peaks["stages"], "peak_fit_mb": peaks.get("fit", float("nan")),
        "ru_maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }  # fmt: skip


def _fit(sampler: PeakSampler, model, res) -> dict:
    """The chunked SMPL fit (step I) of ``res``'s smoothed tracks, if ``model``."""
    if model is None:
        return {}
    from pipeline.fit.chunks import fit_in_chunks

    sampler.stage("fit")
    t1 = time.process_time()
    f1, _ = fit_in_chunks(res.track_smoothed, res.joint_set, model, progress=False)
    return {
        "fit_cpu_s": time.process_time() - t1,
        "person_frames": int(f1.present.sum()),
        "fit_residual_mm": float(np.nanmean(f1.residual)),
    }


def child(scene_dir: str, frames: int, mode: str, chunk: int) -> dict:
    """One measurement (run in its own process)."""
    from pipeline.config import PipelineConfig
    from pipeline.data.scene import load_scene
    from pipeline.run.chunked import run_stages_chunked
    from pipeline.run.frames import run_frames, select_2d
    from pipeline.run.pipeline import pack_run

    config = PipelineConfig()
    model = None
    if mode == "fit":  # torch and the body model (~200 MB) before the stages' window
        from pipeline.body.model import load_body_model

        model = load_body_model()
    scene = tiled_scene(load_scene(scene_dir), frames)
    j2d = select_2d(scene, config, None)
    sampler = PeakSampler()
    t0 = time.process_time()
    sampler.stage("before")
    sampler.stage("stages")
    if mode == "keep":
        frames_kept = run_frames(scene, config, j2d, progress=False)
        res = pack_run(scene, frames_kept, config, j2d, restored=None)
        del frames_kept
    else:
        res = run_stages_chunked(
            scene, config, j2d, restored=None, chunk_frames=chunk or 256,
            keep_edges=mode == "chunked",
            progress=False,
        )  # fmt: skip
    t_stages = time.process_time() - t0
    fit = _fit(sampler, model, res)
    peaks = sampler.stop()
    return {
        "frames": frames, "mode": mode, "rows": len(scene.detections),
        "person_frames_found": len(res.person_frame), "edges": len(res.edge_a),
        "tracks": res.num_tracks, "rss_before_mb": peaks["before"],
        "peak_stages_mb": peaks["stages"], "peak_fit_mb": peaks.get("fit", float("nan")),
        "ru_maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "stages_cpu_s": t_stages, **fit,
    }  # fmt: skip


def dome_dir(cache: Path, cams: int, people: int, frames: int) -> Path:
    out = cache / f"dome{cams}_p{people}_f{frames}"
    if not (out / "scene.json").exists():
        from pipeline.body.model import load_body_model
        from pipeline.synth.rigs import dome_capture_radius, dome_rig
        from pipeline.synth.scene_gen import SynthConfig, write_synth_scene

        cfg = SynthConfig(
            num_people=people, num_frames=frames, seed=cams * 100 + people,
            render_video=False, area_radius_mm=dome_capture_radius(5000.0), occlusion="proxy",
        )  # fmt: skip
        write_synth_scene(out, dome_rig(cams, radius_mm=5000.0), load_body_model(), cfg,
                          progress=False)  # fmt: skip
    return out


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, nargs="+", default=[1000, 2500, 5000, 10000])
    modes = ["keep", "chunked", "lean", "fit", "stream", "streamfit", "streamedges"]
    parser.add_argument("--modes", nargs="+", default=["keep", "chunked", "lean"], choices=modes)
    parser.add_argument(
        "--chunk",
        type=int,
        default=0,
        help="frames per chunk (0: each mode's default, 256 / 64 streamed)",
    )
    parser.add_argument("--dome", action="store_true", help="tile a synthesised dome scene")
    parser.add_argument("--dome-frames", type=int, default=10)
    parser.add_argument("--cameras", type=int, default=31)
    parser.add_argument("--people", type=int, default=20)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/mvviz_bench_memory"))
    parser.add_argument("--json", type=Path)
    parser.add_argument("--child", nargs=4, metavar=("SCENE", "FRAMES", "MODE", "CHUNK"),
                        help=argparse.SUPPRESS)  # fmt: skip
    args = parser.parse_args()
    if args.child:
        scene_dir, frames, mode, chunk = args.child
        if mode.startswith("stream"):
            print(json.dumps(child_streamed(scene_dir, mode, int(chunk))))
        else:
            print(json.dumps(child(scene_dir, int(frames), mode, int(chunk))))
        return
    scene_dir = (
        dome_dir(args.cache, args.cameras, args.people, args.dome_frames)
        if args.dome
        else REPO / "sample_data" / "shelf_synth"
    )
    print(f"base scene {scene_dir}; chunk {args.chunk or 'default'} frames", flush=True)
    runs = []
    for frames in args.frames:
        for mode in args.modes:  # alternated per frame count
            src = scene_dir
            if mode.startswith("stream"):  # the tiled scene on disk, read lazily
                src = write_tiled_scene(
                    scene_dir, frames, args.cache / f"{scene_dir.name}_x{frames}"
                )
            cmd = [sys.executable, __file__, "--child", str(src), str(frames), mode,
                   str(args.chunk)]  # fmt: skip
            out = subprocess.run(cmd, capture_output=True, text=True, check=True)
            r = json.loads(out.stdout.strip().splitlines()[-1])
            runs.append(r)
            print(
                f"{frames:6d} frames {mode:8s} rows {r['rows']:9d} edges {r['edges']:10d}  "
                f"before {r['rss_before_mb']:7.1f} MB  stages peak {r['peak_stages_mb']:7.1f} MB"
                f"  fit peak {r['peak_fit_mb']:7.1f} MB  ({r['stages_cpu_s']:.1f} CPU s"
                + (
                    f", fit {r['fit_cpu_s']:.1f} CPU s, {r['person_frames']} pf"
                    if "fit_cpu_s" in r
                    else ""
                )
                + ")",  # fmt: skip
                flush=True,
            )
    slopes = {}
    for mode in args.modes:
        rs = [r for r in runs if r["mode"] == mode]
        if len(rs) >= 2:
            f = np.array([r["frames"] for r in rs], float)
            for key in ("rss_before_mb", "peak_stages_mb", "peak_fit_mb"):
                y = np.array([r[key] for r in rs])
                if np.isfinite(y).all():
                    slopes[f"{mode}_{key}_kb_per_frame"] = float(np.polyfit(f, y, 1)[0] * 1024)
    for k, v in slopes.items():
        print(f"growth {k}: {v:.1f} KB/frame")
    if args.json:
        from bench.common import write_json

        write_json(args.json, {"scene": str(scene_dir), "runs": runs, "slopes": slopes})


if __name__ == "__main__":
    main()
