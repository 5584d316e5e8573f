"""The real Shelf benchmark: our stages against 4D Association's result, one scorer.

Reads ``../shared/data/shelf_real`` (real OpenPose BODY_25 detections on the real Shelf
videos, the real calibration, Shelf's ground truth and 4D Association's (CVPR 2020) own
3D result on the same detections; never shipped: it skips with a message when absent),
converts it with ``mvviz convert``'s importer, runs the pipeline with default settings
and scores every stage and the peer by the Shelf protocol
(:mod:`pipeline.evaluation.protocol`: PCP per actor and per limb, the average over
actors 1-3, MPJPE of the 14 joints). Also: the number of tracks (all, and of 20 frames
or more), how many tracks followed each annotated actor (the tracks nearest to it over
its frames), and the run time.

Usage:
    python bench/bench_peer_shelf.py [--data DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import publish, write_json  # noqa: E402
from pipeline.body.model import load_body_model  # noqa: E402
from pipeline.config import PipelineConfig  # noqa: E402
from pipeline.data.joint_sets import get_joint_set  # noqa: E402
from pipeline.data.scene import load_scene  # noqa: E402
from pipeline.evaluation.evaluate import stage_tracks  # noqa: E402
from pipeline.evaluation.protocol import (  # noqa: E402
    estimates_by_frame,
    format_protocol_table,
    nearest_estimate,
    protocol_joints,
    read_protocol_gt,
    score_protocol,
)
from pipeline.importers import convert_scene  # noqa: E402
from pipeline.importers.fourdag import SKEL19, read_fourdag_skeletons  # noqa: E402
from pipeline.run.pipeline import run_pipeline  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data" / "shelf_real"
PUBLISHED = {  # PCP averages on the whole Shelf, each paper's own scoring
    "MVPose": 96.9, "VoxelPose": 97.0, "MvP": 97.4, "4D Association (paper)": 97.6,
    "Faster VoxelPose": 97.6, "MVGFormer (fine-tuned)": 98.0,
    "triangulation + EKF + SMPL/VPoser (Feiz et al. 2025)": 98.6,
}  # fmt: skip


def peer_estimates(path: Path) -> dict[int, np.ndarray]:
    """frame -> (P, 15, 3) 4D Association's people in the protocol's joints (same rule)."""
    peer = read_fourdag_skeletons(path)
    poses = protocol_joints(peer.joints, SKEL19)
    return {int(f): poses[peer.frame == f] for f in np.unique(peer.frame)}


def tracks_per_actor(tracks: np.ndarray, joint_set, truth) -> dict[int, int]:
    """Actor -> how many distinct tracks were the nearest estimate over its frames."""
    poses = protocol_joints(tracks, joint_set)  # (K, F, 15, 3)
    present = np.isfinite(tracks).all(-1).any(-1)
    used: dict[int, set[int]] = {}
    for f, a, gt in zip(truth.frame, truth.actor, truth.joints, strict=True):
        ids = np.flatnonzero(present[:, f])
        k, _ = nearest_estimate(poses[ids, f], gt)
        if k >= 0:
            used.setdefault(int(a), set()).add(int(ids[k]))
    return {a: len(v) for a, v in used.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--docs", action="store_true", help="write the documentation's section")
    args = ap.parse_args()
    if not (args.data / "openpose").is_dir():
        print(f"skipped: {args.data} (the real Shelf data) is absent")
        return 0
    truth = read_protocol_gt(args.data / "gt_shelf15.npz")
    with tempfile.TemporaryDirectory() as tmp:
        scene_dir = convert_scene(
            calib_format="pose2sim", calib_paths=[args.data / "Calib.toml"],
            out_dir=Path(tmp) / "shelf", detections_format="openpose",
            detections_path=args.data / "openpose",
        )  # fmt: skip
        scene = load_scene(scene_dir)
        model = load_body_model()
        t0 = time.perf_counter()
        results = run_pipeline(scene, PipelineConfig(), model, progress=False)
        took = time.perf_counter() - t0
    js = get_joint_set(results.joint_set)
    scores = {
        name: score_protocol(estimates_by_frame(tracks, js), truth)
        for name, tracks in stage_tracks(results).items()
    }
    scores["4D Association"] = score_protocol(
        peer_estimates(args.data / "peer_4d_association_skel19.txt"), truth
    )
    print(f"Shelf, real OpenPose detections: {scene.num_frames} frames, "
          f"{len(truth.frame)} annotated actor-frames; pipeline {took:.1f} s")  # fmt: skip
    print(format_protocol_table(scores))
    lengths = np.isfinite(results.track_raw).all(-1).any(-1).sum(1)
    per_actor = tracks_per_actor(results.track_smoothed, js, truth)
    print(f"tracks: {results.num_tracks} ({int((lengths >= 20).sum())} of 20 frames or more); "
          f"tracks that followed each actor: "
          + ", ".join(f"actor {a + 1}: {n}" for a, n in sorted(per_actor.items())))  # fmt: skip
    print("published PCP averages (whole Shelf, each paper's scoring): "
          + ", ".join(f"{k} {v}" for k, v in PUBLISHED.items()))  # fmt: skip
    if args.json:
        write_json(args.json, {
            "frames": scene.num_frames,
            "seconds": took,
            "stages": {name: s.as_dict() for name, s in scores.items()},
            "tracks": {"count": int(results.num_tracks), "long": int((lengths >= 20).sum()),
                       "per_actor": {str(a): n for a, n in per_actor.items()}},
            "published": PUBLISHED,
        })  # fmt: skip
    if args.docs:
        long_tracks = int((lengths >= 20).sum())
        body = (
            f"Real OpenPose BODY_25 detections on the real Shelf videos ({scene.num_frames} "
            f"frames, {len(truth.frame)} annotated actor-frames; the data is not shipped), "
            "default settings; every row scored by the same function "
            "(`pipeline/evaluation/protocol.py`, the Shelf protocol's PCP, %).\n\n"
            + format_protocol_table(scores) + "\n\n"
            f"Tracks: {results.num_tracks}, {long_tracks} of 20 frames or more; tracks that "
            "followed each annotated actor: "
            + ", ".join(f"actor {a + 1}: {n}" for a, n in sorted(per_actor.items()))
            + f". Pipeline {took:.1f} s.\n\nPublished PCP averages (whole Shelf, each "
            "paper's own scoring): " + ", ".join(f"{k} {v}" for k, v in PUBLISHED.items()) + "."
        )
        publish("bench_peer_shelf", "The real Shelf benchmark", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
