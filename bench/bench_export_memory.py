"""Memory of ``export_rrd`` against the number of frames exported, three ways, the same run,
alternated: meshes sent in chunks, rows cut into chunks when the export flushes
(:func:`mvviz.export.rrd.export_batcher`) and the C heap trimmed after each chunk
(:func:`mvviz.export.heap.release_free_heap`) (the product's: ``chunked``,
``mesh_chunk_frames`` = :data:`mvviz.export.rrd.MESH_CHUNK_FRAMES`); in chunks on rerun's
default 200 ms clock without the trim (``before``); all at once (``at_once``,
``mesh_chunk_frames=0``); and the product's without rerun's chunk index, the
file's footer (``no_index``: not a product option, as ``rerun rrd verify`` refuses such a
file; it shows what the index, which rerun builds in memory until the file closes, holds).

Each export runs in a fresh process on ``--scene`` (default the shipped sample,
``sample_data/shelf_synth``:
5 cameras, 4 people, 250 frames, ground-truth SMPL meshes and two fitted-body stages),
without images (the pictures already went out frame by frame; this measures the
meshes). Memory: the process's peak resident set during the export alone (its high-water
mark ``VmHWM`` reset through ``/proc/self/clear_refs`` just before, minus ``VmRSS``
then; it includes one chunk's transient skinning buffers, so it varies by +-20 MB from run
to run) and what the export holds once everything is sent, before the recording closes
(``held``: live anonymous memory after a heap trim, what accumulates with the frames),
and the peaks of anonymous memory and of file pages apart, sampled every 5 ms (a results
directory is memory-mapped: the pages read stay resident and count in ``VmHWM``, but
the kernel takes them back when memory is short).
Printed per mode: the medians over --repeats at each frame count, the slope in KB
per frame exported (least squares), what that slope gives at 10,000 frames of 20 people
(x20 / the scene's tracks), the export's seconds, and each older mode's growth against
``chunked``'s.

Usage:
    python bench/bench_export_memory.py [--scene DIR] [--frames 64 128 250] [--repeats 3]
        [--modes chunked before at_once] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.common import write_json  # noqa: E402

SCENE = REPO / "sample_data" / "shelf_synth"

CHILD = r"""
import json, sys, time
from pathlib import Path
from mvviz.export.rrd import export_rrd
from pipeline.body.model import load_body_model
from pipeline.config import PipelineConfig
from pipeline.run.pipeline import run_or_load
from pipeline.data.scene import load_scene

scene_dir, frames, chunk, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
mode = sys.argv[5]
if mode in ("before", "at_once"):  # no heap trim, rerun's 200 ms clock
    import rerun as rr
    import mvviz.export.rerun.logger, mvviz.export.rrd
    mvviz.export.rerun.logger.release_free_heap = lambda: False
    mvviz.export.rerun.logger.release_pages = lambda arr: False  # read pages kept
    mvviz.export.rrd.export_batcher = rr.ChunkBatcherConfig.DEFAULT
    send_plots = mvviz.export.rerun.logger.SceneLogger.send_plots  # and the plots at once
    mvviz.export.rerun.logger.SceneLogger.send_plots = (
        lambda self, *a, **k: send_plots(self, *a, **{**k, "chunk_frames": 0}))
if mode == "no_index":  # the product's, without rerun's chunk index at the end of the file
    import rerun as rr
    save = rr.RecordingStream.save
    rr.RecordingStream.save = lambda self, *a, **k: save(self, *a, **{**k, "write_footer": False})
model = load_body_model()
scene = load_scene(scene_dir)
results, _ = run_or_load(scene, PipelineConfig(), model, progress=False)

def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key + ":"):
            return int(line.split()[1])  # kB

# What the export holds once everything is sent, just before the recording closes (what
# accumulates shows here; the free heap is trimmed first so that only live memory counts).
import mvviz.export.rrd as R
from mvviz.export.heap import release_free_heap
held, complete = {}, R._complete
def measured_complete(rec, tmp, path):
    rec.flush()
    release_free_heap(0)
    held["mb"] = (status("RssAnon") - anon) / 1024
    complete(rec, tmp, path)
R._complete = measured_complete

# The peak of anonymous memory apart from file pages (a results directory is memory-mapped:
# the pages read stay resident, counted in VmHWM, and the kernel takes them back at need).
import threading
peak_anon, peak_file, sampling = [0], [0], [True]
def sample():
    while sampling[0]:
        peak_anon[0] = max(peak_anon[0], status("RssAnon"))
        peak_file[0] = max(peak_file[0], status("RssFile"))
        time.sleep(0.005)

release_free_heap(0)  # the baseline without what loading freed: a later trim cannot go below it
with open("/proc/self/clear_refs", "w") as fh:
    fh.write("5")  # reset the peak resident set (VmHWM) to the current one
before, anon, file_rss = status("VmRSS"), status("RssAnon"), status("RssFile")
sampler = threading.Thread(target=sample, daemon=True)
sampler.start()
t0 = time.perf_counter()
export_rrd(scene, results, model, out, frames=range(frames), images=False,
           mesh_chunk_frames=chunk, progress=False)
sampling[0] = False
sampler.join()
print(json.dumps({"growth_mb": (status("VmHWM") - before) / 1024, "people": results.num_tracks,
                  "held_mb": held["mb"], "anon_peak_mb": (peak_anon[0] - anon) / 1024,
                  "file_peak_mb": (peak_file[0] - file_rss) / 1024,
                  "seconds": time.perf_counter() - t0,
                  "file_mb": Path(out).stat().st_size / 1e6}))
"""


def run_child(scene: Path, frames: int, chunk: int, mode: str, out: Path) -> dict:
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, str(scene), str(frames), str(chunk), str(out), mode],
        capture_output=True, text=True, cwd=REPO, check=False,
    )  # fmt: skip
    if proc.returncode != 0:
        raise SystemExit(f"export of {frames} frames (chunk {chunk}) failed:\n{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[64, 128, 250])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scene", type=Path, default=SCENE, help="default: the shipped sample")
    ap.add_argument("--modes", nargs="+", default=["chunked", "before", "at_once"],
                    choices=["chunked", "before", "at_once", "no_index"])  # fmt: skip
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    from mvviz.export.rrd import MESH_CHUNK_FRAMES

    modes = {"chunked": MESH_CHUNK_FRAMES, "before": MESH_CHUNK_FRAMES, "at_once": 0,
             "no_index": MESH_CHUNK_FRAMES}  # fmt: skip
    modes = {m: v for m, v in modes.items() if m in args.modes}
    runs: dict[str, dict[int, list[dict]]] = {m: {f: [] for f in args.frames} for m in modes}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            for f in args.frames:
                order = list(modes.items()) if r % 2 == 0 else list(reversed(modes.items()))
                for m, chunk in order:
                    row = run_child(args.scene, f, chunk, m, Path(tmp) / f"{m}_{f}.rrd")
                    runs[m][f].append(row)
                    print(f"repeat {r + 1}: {f:4d} frames, {m:8s}: +{row['growth_mb']:7.1f} MB "
                          f"peak ({row['anon_peak_mb']:.1f} anonymous, {row['file_peak_mb']:.1f} "
                          f"file pages), {row['held_mb']:6.1f} MB held at the end, in "
                          f"{row['seconds']:.1f} s, file {row['file_mb']:.1f} MB",
                          flush=True)  # fmt: skip
    print(
        f"\nscene: {args.scene.name}, chunk {MESH_CHUNK_FRAMES} frames; medians of {args.repeats}"
    )
    out: dict = {"chunk_frames": MESH_CHUNK_FRAMES, "frames": args.frames, "modes": {}}
    for m in modes:
        med = [statistics.median(x["growth_mb"] for x in runs[m][f]) for f in args.frames]
        slope_kb = float(np.polyfit(args.frames, med, 1)[0]) * 1024
        # between the two longest exports: past the first chunk, what a frame adds
        tail_kb = (med[-1] - med[-2]) / (args.frames[-1] - args.frames[-2]) * 1024
        people = max(runs[m][args.frames[-1]][0]["people"], 1)  # the scene's tracks
        at_10k = max(tail_kb, 0.0) * 10_000 * 20 / people / 1024**2  # GB: 10,000 x 20 people
        secs = [statistics.median(x["seconds"] for x in runs[m][f]) for f in args.frames]
        held = [statistics.median(x["held_mb"] for x in runs[m][f]) for f in args.frames]
        held_kb = float(np.polyfit(args.frames, held, 1)[0]) * 1024
        anon = [statistics.median(x["anon_peak_mb"] for x in runs[m][f]) for f in args.frames]
        anon_kb = float(np.polyfit(args.frames, anon, 1)[0]) * 1024
        print(f"{m:8s}: anonymous peak {' / '.join(f'{v:.1f}' for v in anon)} MB "
              f"({anon_kb:.1f} KB a frame, fit); held at the end "
              f"{' / '.join(f'{v:.1f}' for v in held)} MB "
              f"({held_kb:.1f} KB a frame, fit); peak growth "
              f"{' / '.join(f'{v:.1f}' for v in med)} MB at "
              f"{' / '.join(map(str, args.frames))} frames; {slope_kb:.0f} KB a frame (fit), "
              f"{tail_kb:.0f} between the last two (~{at_10k:.2f} GB more at 10,000 frames "
              f"x 20 people); export "
              f"{' / '.join(f'{s:.1f}' for s in secs)} s")  # fmt: skip
        out["modes"][m] = {"growth_mb": med, "kb_per_frame": slope_kb, "tail_kb_per_frame": tail_kb,
                           "gb_at_10k_20p": at_10k, "seconds": secs, "held_mb": held,
                           "held_kb_per_frame": held_kb, "anon_peak_mb": anon,
                           "anon_kb_per_frame": anon_kb}  # fmt: skip
    for m in [m for m in ("at_once", "before", "no_index") if m in modes and "chunked" in modes]:
        a, b = (out["modes"][k]["growth_mb"] for k in (m, "chunked"))
        print(f"growth at {args.frames[-1]} frames: {m} / chunked = {a[-1] / b[-1]:.2f}x; "
              f"from {args.frames[0]} to {args.frames[-1]} frames: {m} +{a[-1] - a[0]:.1f} MB, "
              f"chunked +{b[-1] - b[0]:.1f} MB")  # fmt: skip
    if args.json:
        write_json(args.json, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
