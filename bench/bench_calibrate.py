"""Benchmark ``mvviz calibrate`` (pipeline.calibrate) against Caliscope's own calibration
of the same four real webcams (/work/shared/data/caliscope_charuco: a 4x5 ChArUco board of
54 mm squares walked through the views, 111 synchronised frames per camera; Caliscope's
``camera_array.toml``, BSD-2-Clause, read in place).

Three runs: from scratch (our intrinsics from the same footage), with Caliscope's
intrinsics (``--intrinsics camera_array.toml``: the poses only), and with its intrinsics
and the cameras held as synchronised as the table says (``--fixed-sync``). Per run it
prints:

- per camera: focal lengths and principal point (ours / Caliscope's), the board-corner
  reprojection RMS of our bundle adjustment (px);
- per camera pair: the relative rotation's difference from Caliscope's (deg), the
  difference of the relative translation (mm) and both baselines (mm);
- the board triangulated from every frame two or more cameras see it in: the median
  absolute error of adjacent-corner distances against the printed 54 mm (ours and
  Caliscope's calibration on the same corners), once with the frames matched as the sync
  table says and once re-matched by the whole frames of the time offsets our bundle
  adjustment estimated (one camera's frames are 0.84 frame early against the table: as
  stamped, its view of the moving board is from another moment than the others'; the
  fixed-sync run is re-matched by the offsets the run with Caliscope's intrinsics found);
- per camera the estimated time offset against the sync table (ms);
- seconds per step.

Poses are compared relative to each other (the world frames differ). Skips with a message
when the data is absent.

Usage:
    python bench/bench_calibrate.py [--data DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import markdown_table, publish, write_json  # noqa: E402
from pipeline.calibrate.board import parse_board  # noqa: E402
from pipeline.calibrate.calibrate import calibrate_cameras  # noqa: E402
from pipeline.data.cameras import CameraRig  # noqa: E402
from pipeline.importers.calibration import read_caliscope_calibration  # noqa: E402

DEFAULT_DATA = Path(
    os.environ.get("MVVIZ_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
) / "caliscope_charuco"  # fmt: skip


def relative(a, b) -> tuple[np.ndarray, np.ndarray]:
    R = b.R @ a.R.T
    return R, b.t - R @ a.t


def angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def triangulate(rig: CameraRig, cams: list[int], pixels: list[np.ndarray]) -> np.ndarray:
    """(3,) DLT of one point seen at (2,) distorted pixels by cameras ``cams``."""
    rows = []
    for c, px in zip(cams, pixels, strict=True):
        u, v = rig[c].undistort_pixels(px[None])[0]
        P = rig[c].P
        rows += [u * P[2] - P[0], v * P[2] - P[1]]
    _, _, vt = np.linalg.svd(np.asarray(rows))
    return vt[-1, :3] / vt[-1, 3]


def adjacent_errors(rig: CameraRig, cal, board, *, shift: list[int] | None = None) -> np.ndarray:
    """|distance - square| (mm) of every adjacent pair of corners triangulated in a frame;
    ``shift``: per camera, frames its views are moved by."""
    by_frame: dict[int, dict[int, list]] = {}
    for v in cal.views:
        r = cal.reports[v.camera]
        if r.problem is None:
            frame = v.frame + (shift[v.camera] if shift else 0)
            for i, p in zip(v.ids, v.pixels, strict=True):
                by_frame.setdefault(frame, {}).setdefault(int(i), []).append((v.camera, p))
    cols = board.columns - 1
    errs = []
    for corners in by_frame.values():
        X = {i: triangulate(rig, [c for c, _ in s], [p for _, p in s])
             for i, s in corners.items() if len(s) >= 2}  # fmt: skip
        for i in X:
            for j in (i + 1, i + cols):
                if j in X and (j != i + 1 or (i + 1) % cols):
                    errs.append(abs(np.linalg.norm(X[i] - X[j]) - board.square_mm))
    return np.asarray(errs)


def run(
    data: Path, board, peer: CameraRig, *, with_intrinsics: bool, fixed_sync: bool = False,
    shift: list[int] | None = None,
) -> dict:  # fmt: skip
    """One calibration and its figures; ``shift``: the whole frames to re-match each
    camera's views by (default: this run's estimated offsets, rounded)."""
    videos = [data / "extrinsic" / f"cam_{k}.mp4" for k in range(4)]
    t0 = time.perf_counter()
    cal = calibrate_cameras(videos, board, sync=data / "extrinsic" / "timestamps.csv",
                            intrinsics=peer if with_intrinsics else None,
                            sync_offsets=not fixed_sync)  # fmt: skip
    total = time.perf_counter() - t0
    ours = cal.rig
    out: dict = {"seconds": {**cal.seconds, "total": total}, "cameras": {}, "pairs": {}}
    for r, cam in zip(cal.reports, ours, strict=True):
        p = peer[peer.index_of(cam.name)]
        out["cameras"][cam.name] = {
            "fx": cam.K[0, 0], "fy": cam.K[1, 1], "cx": cam.K[0, 2], "cy": cam.K[1, 2],
            "peer_fx": p.K[0, 0], "peer_fy": p.K[1, 1], "peer_cx": p.K[0, 2], "peer_cy": p.K[1, 2],
            "focal_diff_pct": 100 * (cam.K[0, 0] / p.K[0, 0] - 1),
            "ba_rms_px": r.ba_rms, "intrinsic_rms_px": r.intrinsic_rms,
            "board_frames": r.board_frames, "intrinsic_views": r.intrinsic_views,
            "sync_offset_ms": 1000 * r.sync_offset_s,
        }  # fmt: skip
    for i, j in itertools.combinations(range(len(ours)), 2):
        R, t = relative(ours[i], ours[j])
        pi, pj = peer.index_of(ours[i].name), peer.index_of(ours[j].name)
        R0, t0 = relative(peer[pi], peer[pj])
        out["pairs"][f"{ours[i].name}-{ours[j].name}"] = {
            "rotation_diff_deg": angle_deg(R @ R0.T),
            "translation_diff_mm": float(np.linalg.norm(t - t0)),
            "baseline_mm": float(np.linalg.norm(t)), "peer_baseline_mm": float(np.linalg.norm(t0)),
        }  # fmt: skip
    peer_in_order = CameraRig(tuple(peer[peer.index_of(c.name)] for c in ours))
    if shift is None:
        shift = [int(round(r.sync_offset_frames)) if r.problem is None else 0
                 for r in cal.reports]  # fmt: skip
    out["resync_shift_frames"] = shift
    for key, by in (("adjacent_corners", None), ("adjacent_corners_resynced", shift)):
        ours_err = adjacent_errors(ours, cal, board, shift=by)
        peer_err = adjacent_errors(peer_in_order, cal, board, shift=by)
        out[key] = {
            "pairs": len(ours_err),
            "ours_median_abs_err_mm": float(np.median(ours_err)),
            "peer_median_abs_err_mm": float(np.median(peer_err)),
        }
    return out


def report(name: str, res: dict) -> None:
    steps = ", ".join(f"{k} {v:.1f} s" for k, v in res["seconds"].items() if k != "total")
    print(f"\n== {name}: {res['seconds']['total']:.1f} s ({steps})")
    print(f"{'camera':<7} {'fx ours/peer':>16} {'diff %':>7} {'cx, cy ours':>14} "
          f"{'cx, cy peer':>14} {'BA RMS px':>10} {'offset ms':>10}")  # fmt: skip
    for n, c in res["cameras"].items():
        print(f"{n:<7} {c['fx']:>7.1f} /{c['peer_fx']:>7.1f} {c['focal_diff_pct']:>+7.2f} "
              f"{c['cx']:>6.1f},{c['cy']:>6.1f} {c['peer_cx']:>6.1f},{c['peer_cy']:>6.1f} "
              f"{c['ba_rms_px']:>10.3f} {c['sync_offset_ms']:>+10.1f}")  # fmt: skip
    print(f"{'pair':<12} {'rot diff deg':>12} {'t diff mm':>10} {'baseline ours/peer mm':>22}")
    for n, p in res["pairs"].items():
        print(f"{n:<12} {p['rotation_diff_deg']:>12.2f} {p['translation_diff_mm']:>10.1f} "
              f"{p['baseline_mm']:>10.1f} /{p['peer_baseline_mm']:>8.1f}")  # fmt: skip
    for key, how in (
        ("adjacent_corners", "frames as the sync table matches them"),
        ("adjacent_corners_resynced", "frames re-matched by the offsets, whole frames"),
    ):
        a = res[key]
        print(
            f"adjacent corners vs 54 mm ({a['pairs']} pairs, {how}), median |error|: ours "
            f"{a['ours_median_abs_err_mm']:.3f} mm, Caliscope's "
            f"{a['peer_median_abs_err_mm']:.3f} mm"
        )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--docs", action="store_true", help="write the documentation's section")
    args = ap.parse_args()
    if not (args.data / "camera_array.toml").is_file():
        print(f"skipped: the Caliscope session is not at {args.data}")
        return 0
    board = parse_board(args.data / "charuco.toml")
    peer = read_caliscope_calibration(args.data / "camera_array.toml")
    figures = {
        "from_scratch": run(args.data, board, peer, with_intrinsics=False),
        "caliscope_intrinsics": run(args.data, board, peer, with_intrinsics=True),
    }  # fmt: skip
    figures["caliscope_intrinsics_fixed_sync"] = run(
        args.data, board, peer, with_intrinsics=True, fixed_sync=True,
        shift=figures["caliscope_intrinsics"]["resync_shift_frames"],
    )  # fmt: skip
    for name, res in figures.items():
        report(name, res)
    if args.json:
        write_json(args.json, figures)
    if args.docs:
        publish("bench_calibrate", "Calibration against Caliscope's", docs_section(figures))
    return 0


def docs_section(figures: dict) -> str:
    """The Benchmarks page's section: one column per way of calibrating."""
    names = {"from_scratch": "from scratch", "caliscope_intrinsics": "Caliscope's intrinsics",
             "caliscope_intrinsics_fixed_sync": "its intrinsics, `--fixed-sync`"}  # fmt: skip
    cols = [k for k in names if k in figures]

    def row(label, fn):
        return [label, *(fn(figures[k]) for k in cols)]

    def span(values, fmt):
        values = list(values)
        return f"{fmt.format(min(values))}-{fmt.format(max(values))}"

    rows = [
        row("focal length vs Caliscope's, %", lambda r: " / ".join(
            f"{c['focal_diff_pct']:+.1f}" for c in r["cameras"].values())),
        row("bundle-adjustment RMS per camera, px", lambda r: " / ".join(
            f"{c['ba_rms_px']:.2f}" for c in r["cameras"].values())),
        row("time offsets, ms", lambda r: " / ".join(
            f"{c['sync_offset_ms']:+.0f}" for c in r["cameras"].values())),
        row("pair rotations vs Caliscope's, deg", lambda r: span(
            (p["rotation_diff_deg"] for p in r["pairs"].values()), "{:.2f}")),
        row("pair translations vs Caliscope's, mm", lambda r: span(
            (p["translation_diff_mm"] for p in r["pairs"].values()), "{:.1f}")),
        row("board: adjacent corners vs 54 mm, median abs. error, frames as matched (Caliscope's)",
            lambda r: f"{r['adjacent_corners']['ours_median_abs_err_mm']:.2f} mm "
                      f"({r['adjacent_corners']['peer_median_abs_err_mm']:.2f})"),
        row("the same, frames re-matched by the offsets found (Caliscope's)",
            lambda r: f"{r['adjacent_corners_resynced']['ours_median_abs_err_mm']:.2f} mm "
                      f"({r['adjacent_corners_resynced']['peer_median_abs_err_mm']:.2f})"),
        row("time, s", lambda r: f"{r['seconds']['total']:.1f}"),
    ]  # fmt: skip
    return (
        "`mvviz calibrate` on Caliscope's four-webcam ChArUco session (1280x720, 111 frames) "
        "against Caliscope's own calibration of the same cameras; cameras in the order "
        + ", ".join(next(iter(figures.values()))["cameras"])
        + ".\n\n"
        + markdown_table(["", *(names[k] for k in cols)], rows)
    )


if __name__ == "__main__":
    sys.exit(main())
