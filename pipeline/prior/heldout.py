"""Held-out discipline for the pose prior: which motion a prior learnt from, which motion
a test scene plays, and the check that they share no frame.

A prior checkpoint records its sources (``info["sources"]``, one record per source:
``file``, ``source_frames`` for a BVH clip, see ``mvviz train-prior``); a scene made
by ``mvviz synth --motion`` records which clip each person plays from which frame
(``scene.json`` ``synth.people``, ``synth.clips``). Frames are compared as
``(clip file name, frame of the BVH file)``: every frame of a training clip is a
training frame, and a scene person playing ``num_frames`` frames from ``start_frame``
at the scene's fps covers every file frame from the first to the last it interpolates.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np


def training_frames(sources: list[dict]) -> set[tuple[str, int]]:
    """(file name, file frame) of every recorded frame a prior was trained on (``sources``
    = a checkpoint's ``info["sources"]``: a BVH clip or a file of fitted poses, each with
    ``source_frames``; generated sources have no file frames and add nothing)."""
    out: set[tuple[str, int]] = set()
    for s in sources:
        name = Path(str(s.get("file", ""))).name
        if name.lower().endswith((".bvh", ".npz")) and "source_frames" in s:
            out.update((name, i) for i in range(int(s["source_frames"])))
    return out


def source_activities(source: dict) -> set[str]:
    """The activities of one training source: its ``activities`` list, else its
    ``activity`` text ("start, walk, stop"; "walk, reach (where)") split at commas, with
    parentheses, "start" and "stop" dropped."""
    if "activities" in source:
        return {str(a) for a in source["activities"]}
    text = re.sub(r"\([^)]*\)", "", str(source.get("activity", "")))
    words = {w.strip() for w in text.split(",")}
    return words - {"", "start", "stop", "unknown"}


def check_activity_held_out(sources: list[dict], activity: str) -> None:
    """Raise ``ValueError`` if any training source of a prior shows ``activity`` (a
    leave-one-activity-out split must not have seen it in any source)."""
    seen = [str(s.get("file", "?")) for s in sources if activity in source_activities(s)]
    if seen:
        raise ValueError(f"the prior was trained on {activity!r} motion (sources {seen})")


def scene_frames(synth: dict) -> set[tuple[str, int]]:
    """(clip file name, file frame) of every BVH frame a mocap scene's people play
    (``synth`` = ``scene.json``'s ``synth`` record of ``mvviz synth --motion``)."""
    clips = {Path(c["file"]).name: c for c in synth.get("clips", [])}
    out: set[tuple[str, int]] = set()
    for p in synth.get("people", []):
        c = clips[p["clip"]]
        ratio = float(c["source_fps"]) / float(c["fps"])
        start, n = int(p["start_frame"]), int(p["num_frames"])
        lo = int(np.floor(start * ratio))
        hi = min(int(np.ceil((start + n - 1) * ratio)), int(c["source_frames"]) - 1)
        out.update((p["clip"], i) for i in range(lo, hi + 1))
    return out


def check_disjoint(sources: list[dict], synth: dict) -> None:
    """Raise ``ValueError`` if a frame a test scene plays is among a prior's training
    frames (training on the test motion is never a held-out result)."""
    shared = training_frames(sources) & scene_frames(synth)
    if shared:
        files = sorted({f for f, _ in shared})
        raise ValueError(
            f"the prior was trained on {len(shared)} frames the scene plays (clips {files})"
        )
