"""Memory of ``export_rrd`` against the number of frames exported, three ways, the same run,
alternated: meshes sent in chunks with the C heap trimmed after each (today: ``chunked``,
``mesh_chunk_frames`` = :data:`mvviz.export.rrd.MESH_CHUNK_FRAMES`,
:func:`mvviz.export.heap.release_free_heap`); in chunks without the trim (``no_trim``, the
export of stops 28-36); all at once (``at_once``, ``mesh_chunk_frames=0``, before stop 28).

Each export runs in a fresh process on the shipped sample (``sample_data/shelf_synth``:
5 cameras, 4 people, 250 frames, ground-truth SMPL meshes and two fitted-body stages),
without images (the pictures already went out frame by frame; this measures the
meshes). Memory: the process's peak resident set during the export alone (its high-water
mark ``VmHWM`` reset through ``/proc/self/clear_refs`` just before, minus ``VmRSS``
then). Printed per mode: the medians over --repeats at each frame count, the slope in KB
per frame exported (least squares), what that slope gives at 10,000 frames of 20 people
(x5 the sample's people), the export's seconds, and each older mode's growth against
``chunked``'s.

Usage:
    python bench/bench_export_memory.py [--frames 64 128 250] [--repeats 3] [--json FILE]
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
from pipeline.body_model import load_body_model
from pipeline.config import PipelineConfig
from pipeline.results import run_or_load
from pipeline.scene import load_scene

scene_dir, frames, chunk, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
if sys.argv[5] == "0":  # the export before the heap was trimmed per chunk
    import mvviz.export.rerun.logger, mvviz.export.rrd
    mvviz.export.rrd.release_free_heap = mvviz.export.rerun.logger.release_free_heap = (
        lambda: False)
model = load_body_model()
scene = load_scene(scene_dir)
results, _ = run_or_load(scene, PipelineConfig(), model, progress=False)

def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key + ":"):
            return int(line.split()[1])  # kB

with open("/proc/self/clear_refs", "w") as fh:
    fh.write("5")  # reset the peak resident set (VmHWM) to the current one
before = status("VmRSS")
t0 = time.perf_counter()
export_rrd(scene, results, model, out, frames=range(frames), images=False,
           mesh_chunk_frames=chunk, progress=False)
print(json.dumps({"growth_mb": (status("VmHWM") - before) / 1024,
                  "seconds": time.perf_counter() - t0,
                  "file_mb": Path(out).stat().st_size / 1e6}))
"""


def run_child(frames: int, chunk: int, trim: bool, out: Path) -> dict:
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, str(SCENE), str(frames), str(chunk), str(out),
         str(int(trim))],
        capture_output=True, text=True, cwd=REPO, check=False,
    )  # fmt: skip
    if proc.returncode != 0:
        raise SystemExit(f"export of {frames} frames (chunk {chunk}) failed:\n{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[64, 128, 250])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    from mvviz.export.rrd import MESH_CHUNK_FRAMES  # noqa: PLC0415

    modes = {"chunked": (MESH_CHUNK_FRAMES, True), "no_trim": (MESH_CHUNK_FRAMES, False),
             "at_once": (0, False)}  # fmt: skip
    runs: dict[str, dict[int, list[dict]]] = {m: {f: [] for f in args.frames} for m in modes}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            for f in args.frames:
                order = list(modes.items()) if r % 2 == 0 else list(reversed(modes.items()))
                for m, (chunk, trim) in order:
                    row = run_child(f, chunk, trim, Path(tmp) / f"{m}_{f}.rrd")
                    runs[m][f].append(row)
                    print(f"repeat {r + 1}: {f:4d} frames, {m:8s}: +{row['growth_mb']:7.1f} MB "
                          f"in {row['seconds']:.1f} s, file {row['file_mb']:.1f} MB",
                          flush=True)  # fmt: skip
    print(f"\nsample: {SCENE.name}, chunk {MESH_CHUNK_FRAMES} frames; medians of {args.repeats}")
    out: dict = {"chunk_frames": MESH_CHUNK_FRAMES, "frames": args.frames, "modes": {}}
    for m in modes:
        med = [statistics.median(x["growth_mb"] for x in runs[m][f]) for f in args.frames]
        slope_kb = float(np.polyfit(args.frames, med, 1)[0]) * 1024
        # between the two longest exports: past the first chunk, what a frame adds
        tail_kb = (med[-1] - med[-2]) / (args.frames[-1] - args.frames[-2]) * 1024
        at_10k = max(tail_kb, 0.0) * 10_000 * 5 / 1024**2  # GB: 10,000 frames, 20 people
        secs = [statistics.median(x["seconds"] for x in runs[m][f]) for f in args.frames]
        print(f"{m:8s}: growth {' / '.join(f'{v:.1f}' for v in med)} MB at "
              f"{' / '.join(map(str, args.frames))} frames; {slope_kb:.0f} KB a frame (fit), "
              f"{tail_kb:.0f} between the last two (~{at_10k:.2f} GB more at 10,000 frames "
              f"x 20 people); export "
              f"{' / '.join(f'{s:.1f}' for s in secs)} s")  # fmt: skip
        out["modes"][m] = {"growth_mb": med, "kb_per_frame": slope_kb, "tail_kb_per_frame": tail_kb,
                           "gb_at_10k_20p": at_10k, "seconds": secs}  # fmt: skip
    for m in ("at_once", "no_trim"):
        a, b = (out["modes"][k]["growth_mb"] for k in (m, "chunked"))
        print(f"growth at {args.frames[-1]} frames: {m} / chunked = {a[-1] / b[-1]:.2f}x; "
              f"from {args.frames[0]} to {args.frames[-1]} frames: {m} +{a[-1] - a[0]:.1f} MB, "
              f"chunked +{b[-1] - b[0]:.1f} MB")  # fmt: skip
    if args.json:
        write_json(args.json, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
