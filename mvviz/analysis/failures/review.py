"""Entries of a criterion merged into spans, ranked and counted, and the camera a jump
to an entry shows (:func:`seeing_view`)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from mvviz.analysis.failures.criteria import (
    association_failures,
    id_failures,
    kalman_failures,
    label_failures,
    mpjpe_failures,
    proportion_failures,
    reprojection_failures,
    smpl_failures,
)
from mvviz.analysis.failures.entries import (
    AFFINITY_THRESHOLD,
    CRITERIA,
    MAHALANOBIS_THRESHOLD,
    MERGE_GAP,
    MERGE_IGNORES,
    UNASSIGNED_CONFIDENCE,
    Failure,
)
from mvviz.analysis.failures.protocol import has_protocol, protocol_failures
from pipeline.data.scene import Scene
from pipeline.results.store import PipelineResults


def find_failures(
    scene: Scene,
    results: PipelineResults,
    *,
    criterion: str,
    top: int = 50,
    mahalanobis_threshold: float = MAHALANOBIS_THRESHOLD,
    affinity_threshold: float = AFFINITY_THRESHOLD,
    unassigned_confidence: float = UNASSIGNED_CONFIDENCE,
) -> list[Failure]:
    """The ``top`` worst entries of ``criterion`` (one of :data:`CRITERIA`), worst first.

    Consecutive frames of one problem (same kind, track, joint and camera; gaps of up to
    :data:`MERGE_GAP` frames bridged) are one entry with its span. Cameras the run
    disabled (``results.config.disabled_views``) are left out. ``mpjpe`` and ID switches
    need ``scene.gt``, ``smpl`` a fit: without them those lists are empty (``id`` still
    lists births and deaths).
    """
    return rank(
        all_failures(
            scene,
            results,
            criterion=criterion,
            mahalanobis_threshold=mahalanobis_threshold,
            affinity_threshold=affinity_threshold,
            unassigned_confidence=unassigned_confidence,
        ),
        top,
    )


def all_failures(
    scene: Scene,
    results: PipelineResults,
    *,
    criterion: str,
    mahalanobis_threshold: float = MAHALANOBIS_THRESHOLD,
    affinity_threshold: float = AFFINITY_THRESHOLD,
    unassigned_confidence: float = UNASSIGNED_CONFIDENCE,
) -> list[Failure]:
    """Every merged entry of ``criterion``, unranked (see :func:`find_failures`)."""
    if criterion not in CRITERIA:
        raise ValueError(f"unknown failure criterion {criterion!r}; expected one of {CRITERIA}")
    if results.num_frames != scene.num_frames or results.num_views != len(scene.rig):
        raise ValueError(
            f"results ({results.num_frames} frames, {results.num_views} views) are not of "
            f"this scene ({scene.num_frames} frames, {len(scene.rig)} views)"
        )
    if criterion == "reprojection":
        found = reprojection_failures(scene, results)
    elif criterion == "mpjpe":
        found = mpjpe_failures(scene, results)
    elif criterion == "association":
        found = association_failures(
            scene,
            results,
            affinity_threshold=affinity_threshold,
            unassigned_confidence=unassigned_confidence,
        )
    elif criterion == "id":
        found = id_failures(scene, results)
    elif criterion == "kalman":
        found = kalman_failures(scene, results, threshold=mahalanobis_threshold)
    elif criterion == "proportions":
        found = proportion_failures(scene, results)
    elif criterion == "labels":
        found = label_failures(scene, results)
    elif criterion == "protocol":
        found = protocol_failures(scene, results)
    else:
        found = smpl_failures(scene, results)
    off = disabled_views(scene, results)
    found = [f for f in found if f.view is None or f.view not in off]
    # a kind "no track|3" merges per GT person 3 and is counted as "no track"
    return [
        dataclasses.replace(f, kind=f.kind.split("|")[0]) if "|" in f.kind else f
        for f in merge_spans(found)
    ]


def disabled_views(scene: Scene, results: PipelineResults) -> set[int]:
    """Indices of the cameras the run left out."""
    off = set(results.config.disabled_views)
    return {v for v, name in enumerate(scene.rig.names) if name in off}


def kind_counts(failures: list[Failure]) -> dict[str, int]:
    """Entries per kind, most first (ties: first seen)."""
    counts: dict[str, int] = {}
    for f in failures:
        counts[f.kind or f.criterion] = counts.get(f.kind or f.criterion, 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: -kv[1]))


def available_criteria(scene: Scene, results: PipelineResults) -> tuple[str, ...]:
    """The criteria that can find something in this scene and run."""
    out = [c for c in CRITERIA if c != "mpjpe" or scene.gt is not None]
    if not has_protocol(scene):
        out.remove("protocol")
    if results.smpl is None and results.smpl_vae is None:
        out.remove("smpl")
    if results.track_contradicted is None:
        out.remove("proportions")  # results of a run without the proportion check
    return tuple(out)


def rank(failures: list[Failure], top: int) -> list[Failure]:
    """Worst first (ties: earlier frame, lower track); NaN scores dropped."""
    ok = [f for f in failures if math.isfinite(f.score)]
    ok.sort(key=lambda f: (-f.score, f.first, f.frame, -1 if f.track is None else f.track))
    return ok[: max(int(top), 0)]


def merge_spans(failures: list[Failure], *, max_gap: int = MERGE_GAP) -> list[Failure]:
    """Entries of one problem (criterion, kind, track, joint, view, less what
    :data:`MERGE_IGNORES` says) on frames at most ``max_gap`` frames apart merged into
    one: its span, the count of frames and the worst frame's score, value and detail.
    Entries that already span frames (a gap) merge only with entries near them likewise."""
    groups: dict[tuple, list[Failure]] = {}
    for f in failures:
        ignores = MERGE_IGNORES.get(f.criterion, ())
        joint = None if "joint" in ignores else f.joint
        view = None if "view" in ignores else f.view
        groups.setdefault((f.criterion, f.kind, f.track, joint, view), []).append(f)
    out = []
    for entries in groups.values():
        entries.sort(key=lambda f: (f.first, f.last))
        run, run_last = [entries[0]], entries[0].last  # the run's last frame so far
        for f in entries[1:]:
            if f.first - run_last <= max_gap + 1:
                run.append(f)
                run_last = max(run_last, f.last)
            else:
                out.append(_merged(run))
                run, run_last = [f], f.last
        out.append(_merged(run))
    return out


def _merged(run: list[Failure]) -> Failure:
    if len(run) == 1:
        return run[0]
    worst = max(run, key=lambda f: (f.score, -f.frame))
    return dataclasses.replace(
        worst,
        first=min(f.first for f in run),
        last=max(f.last for f in run),
        frames=len(set().union(*(range(f.first, f.last + 1) for f in run))),
    )


def seeing_view(scene: Scene, results: PipelineResults, failure: Failure) -> int | None:
    """The camera to show for ``failure``: its own view if it names one; else, for a
    track, the enabled camera whose detection of that person at the failure's frame is
    most confident; else (the track is missing there) the enabled camera in whose image
    the track's nearest known pose lands most fully, nearest first. None without a track
    or a camera that sees it."""
    if failure.view is not None:
        return failure.view
    k, f = failure.track, failure.frame
    if k is None or not 0 <= k < results.num_tracks:
        return None
    off = disabled_views(scene, results)
    q = np.flatnonzero((results.person_frame == f) & (results.person_track == k))
    if len(q):
        members = results.person_members[int(q[0])]  # (V,)
        best, best_conf = None, -np.inf
        for v in np.flatnonzero(members >= 0):
            if int(v) in off:
                continue
            c = results.det_joints2d[members[v], :, 2]
            c = float(np.nanmean(c)) if np.isfinite(c).any() else 0.0
            if c > best_conf:
                best, best_conf = int(v), c
        if best is not None:
            return best
    pose = nearest_pose(results, k, f)
    if pose is None:
        return None
    scores = []
    for v, cam in enumerate(scene.rig):
        if v in off:
            continue
        uv = cam.project(pose)  # (J, 2) px, NaN behind
        inside = np.isfinite(uv).all(1)
        inside &= (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0)
        inside &= uv[:, 1] < cam.height
        dist = float(np.linalg.norm(np.nanmean(pose, 0) - cam.center))
        scores.append((-inside.mean(), dist, v))
    scores.sort()
    return scores[0][2] if scores and scores[0][0] < 0 else None


def nearest_pose(results: PipelineResults, track: int, frame: int) -> np.ndarray | None:
    """(J', 3) mm: the finite joints of ``track`` at the frame nearest ``frame`` that has
    any (filtered first, raw else), or None when the track has none."""
    for points in (results.track_filtered[track], results.track_raw[track]):  # (F, J, 3)
        ok = np.isfinite(points).all(-1)  # (F, J)
        frames = np.flatnonzero(ok.any(1))
        if len(frames):
            g = int(frames[np.argmin(np.abs(frames - frame))])
            return points[g][ok[g]]
    return None


# --------------------------------------------------------------------------- notes
