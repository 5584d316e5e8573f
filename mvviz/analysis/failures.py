"""Failure review: rank what went wrong in a run, worst first, and keep notes on frames.

Pure functions over a :class:`~pipeline.scene.Scene` and its
:class:`~pipeline.results.PipelineResults`; the GUI is :mod:`mvviz.panels.failure_panel`.
:func:`find_failures` returns :class:`Failure` entries for one criterion: one per
problem, its consecutive frames merged into a span (``first..last``, the worst frame
``frame`` to jump to), naming, where they apply, the track, the joint (an index into the
results' joint set, ``None`` where that set lacks it) and the view (camera index).
Cameras the run disabled are left out.

========================  ==================================================  ===========
criterion                 a problem (``kind``)                                 score
========================  ==================================================  ===========
``reprojection``          (track, joint, view) whose used error is >= 2x its  error /
                          usual (the run's median of that joint and camera)   usual
``mpjpe``                 (track) whose MPJPE vs its matched ground truth     MPJPE /
                          (Hungarian, the filtered tracks) is >= 2x the       median
                          run's median; GT people / tracks left unmatched
``association``           person pair whose detections look alike, person     see below
                          seen by < 2 views, track gap, confident unassigned
                          detection (per camera)
``id``                    track birth after frame 0, death before the last,   see below
                          ID switch against ground truth
``kalman``                (track) with a joint's Mahalanobis distance above   Mahalanobis
                          the threshold, its worst joint named
``smpl``                  (track, joint) with a fit residual >= 2x that       see below
                          joint's usual; rotation outside its
                          ``pose_limits.LIMITS`` box
``labels``                finding of :mod:`pipeline.label_check` (scene,      measured /
                          track or camera)                                     threshold
========================  ==================================================  ===========

Scores rank entries within one criterion; relative scores (a ratio to the usual level)
keep a camera or joint that is always a bit off from filling a list just under a limit.
``association``: the affinity of a detection to another person's detections (0.5..1),
1 + gap / clip length for a track gap, 1.0 for a one-view person, the mean joint
confidence of an unassigned detection. ``id``: 3 for an ID switch, 1 to 2 for a birth or
death (shorter-lived tracks higher). ``smpl``: residual / usual, or degrees outside the
limits / 10 deg. ``labels``: how far the measure is past its threshold (2 = twice the
allowed fraction; a ratio below its lower bound scores bound / ratio).

Notes (:class:`Note`) are JSON beside the results: ``SCENE/.mvviz/notes.json``.
Units: millimetres and pixels, as in the results.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import warnings
from dataclasses import asdict, dataclass
from datetime import datetime
from pathlib import Path

import numpy as np

from pipeline import metrics, pose_limits
from pipeline.evaluate import _frames_of_gt, evaluate, ground_truth_slots, to_smpl_slots
from pipeline.files import SceneFormatError, atomic_write
from pipeline.joint_sets import SMPL24, get_joint_set, mapping_indices
from pipeline.label_check import check_results
from pipeline.results import PipelineResults
from pipeline.scene import Scene

CRITERIA = ("reprojection", "mpjpe", "association", "id", "kalman", "smpl", "labels")
MAHALANOBIS_THRESHOLD = 3.0
AFFINITY_THRESHOLD = 0.5  # a detection this close to another person's is "close to two"
UNASSIGNED_CONFIDENCE = 0.3  # mean joint confidence of an unassigned detection worth a look
MATCH_GATE_MM = 500.0  # as pipeline.evaluate: pairs above this MPJPE never match
LIMIT_SCALE_DEG = 10.0
SWITCH_SCORE = 3.0
# A measure this many times its usual level (the run's median for that joint and camera)
# is a problem worth listing; entries rank by the ratio, so no list fills up at a limit.
RELATIVE_LEVEL = 2.0
USUAL_FLOOR_PX = 1.0  # usual reprojection errors below this count as 1 px
RESIDUAL_FLOOR_MM = 10.0
MERGE_GAP = 2  # entries of one problem this many frames apart (or fewer) merge
# What one problem is, beyond its kind and track: these criteria merge frames whichever
# joint (Kalman, MPJPE: the track is off) or camera (reprojection: the 3D joint is off,
# so every view shows it) is worst frame by frame, and name the worst frame's.
MERGE_IGNORES = {"kalman": ("joint",), "mpjpe": ("joint",), "reprojection": ("view",)}
NOTES_VERSION = 1


@dataclass(frozen=True)
class Failure:
    """One problem to look at, over a span of frames ``first..last`` (inclusive) of which
    ``frames`` show it; ``frame`` is the worst of them (where a jump goes). ``joint``
    indexes the results' joint set, ``view`` the rig. ``score`` ranks entries within a
    criterion; ``value`` is the measure itself at ``frame`` (px, mm, Mahalanobis ...).
    ``where`` names track, joint and camera (``"track 2 · left_wrist · cam03"``),
    ``detail`` the measure; ``kind`` groups entries within a criterion for the counts.
    """

    criterion: str
    score: float
    frame: int
    track: int | None
    joint: int | None
    view: int | None
    where: str = ""
    detail: str = ""
    kind: str = ""
    first: int = -1  # -1: ``frame``
    last: int = -1
    frames: int = 1
    value: float = math.nan

    def __post_init__(self) -> None:
        if self.first < 0:
            object.__setattr__(self, "first", self.frame)
        if self.last < 0:
            object.__setattr__(self, "last", self.frame)

    @property
    def span(self) -> str:
        """``"f 12"`` or ``"f 140–172"``."""
        return f"f {self.first}" if self.first == self.last else f"f {self.first}–{self.last}"

    @property
    def head(self) -> str:
        """Short enough for a button: the span and the track (else the camera)."""
        who = f"track {self.track}" if self.track is not None else ""
        if not who and self.view is not None:
            who = self.where.split(" · ")[-1] if self.where else ""
        return f"{self.span} · {who}" if who else self.span

    @property
    def text(self) -> str:
        """The whole entry on one line, e.g.
        ``"f 140–152 · track 2 · left_wrist · cam03 · 19.5 px, 4.1× its usual 4.8 px
        (13 frames, worst f 147)"``."""
        parts = [self.span] + [p for p in (self.where, self.detail) if p]
        out = " · ".join(parts)
        if self.first != self.last:
            n = f"{self.frames} frames" if self.frames != self.last - self.first + 1 else ""
            n = n or f"{self.last - self.first + 1} frames"
            out += f" ({n}, worst f {self.frame})"
        return out


def camera_label(name: str) -> str:
    """A camera as the lists name it: ``"cam03"`` as it is, ``"3"`` as ``"cam 3"``."""
    return name if name.lower().startswith(("cam", "view")) else f"cam {name}"


def where_label(track: int | None = None, joint: str | None = None, view: str | None = None) -> str:
    """``"track 2 · left_wrist · cam03"``, leaving out what is None (``view``: a camera name)."""
    parts = [] if track is None else [f"track {track}"]
    parts += [] if joint is None else [joint]
    parts += [] if view is None else [camera_label(view)]
    return " · ".join(parts)


def label(
    frame: int,
    track: int | None = None,
    joint: str | None = None,
    view: str | None = None,
    detail: str = "",
) -> str:
    """``"f 12 · track 2 · left_wrist · cam03 · detail"``, leaving out what is None."""
    return " · ".join(p for p in (f"f {frame}", where_label(track, joint, view), detail) if p)


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
    elif criterion == "labels":
        found = label_failures(scene, results)
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
    if results.smpl is None and results.smpl_vae is None:
        out.remove("smpl")
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
        run = [entries[0]]
        for f in entries[1:]:
            if f.first - max(r.last for r in run) <= max_gap + 1:
                run.append(f)
            else:
                out.append(_merged(run))
                run = [f]
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


def usual_level(values: np.ndarray, axis: int = 0, *, floor: float) -> np.ndarray:
    """The median of ``values`` along ``axis`` (NaN ignored), at least ``floor``; where a
    slice has no finite value, the median of all of them."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices
        med = np.nanmedian(values, axis=axis)
        overall = np.nanmedian(values) if np.isfinite(values).any() else floor
    return np.maximum(np.where(np.isfinite(med), med, overall), floor)


# --------------------------------------------------------------------------- criteria


def _track_or_none(track: int) -> int | None:
    return int(track) if track >= 0 else None


def _joint_names(results: PipelineResults) -> tuple[str, ...]:
    return get_joint_set(results.joint_set).names


def present(results: PipelineResults) -> np.ndarray:
    """(K, F) bool: the track has a raw triangulated joint in the frame."""
    return np.isfinite(results.track_raw).all(-1).any(-1)


def reprojection_failures(
    scene: Scene, results: PipelineResults, *, level: float = RELATIVE_LEVEL
) -> list[Failure]:
    """Each (person-frame, joint, view) triangulation used whose reprojection error is at
    least ``level`` times that joint's usual error in that camera (the median over the
    run, at least :data:`USUAL_FLOOR_PX`); score = error / usual. Ranking by the ratio
    keeps a camera that always reprojects at 18 px (far away, blurry) from filling the
    list just under the outlier threshold, while an error twice its usual stands out."""
    reproj = np.where(results.person_used, results.person_reproj, np.nan)  # (Q, J, V)
    if reproj.shape[0] == 0:
        return []
    usual = usual_level(reproj, 0, floor=USUAL_FLOOR_PX)  # (J, V)
    ratio = reproj / usual
    names, cams = _joint_names(results), scene.rig.names
    out = []
    with np.errstate(invalid="ignore"):
        hits = np.argwhere(ratio >= level)
    for q, j, v in hits:
        f, k = int(results.person_frame[q]), _track_or_none(results.person_track[q])
        e, r = float(reproj[q, j, v]), float(ratio[q, j, v])
        detail = f"{e:.1f} px, {r:.1f}× its usual {usual[j, v]:.1f} px"
        detail += " (untracked person)" if k is None else ""
        out.append(
            Failure(
                "reprojection", r, f, k, int(j), int(v), where_label(k, names[j], cams[v]),
                detail, kind="reprojection", value=e,
            )
        )  # fmt: skip
    return out


def _slot_to_joint(joint_set: str) -> dict[int, int]:
    """SMPL-24 slot -> index in ``joint_set`` (for the joints both name alike)."""
    js = get_joint_set(joint_set)
    src, dst = mapping_indices(js, SMPL24)
    return {int(d): int(s) for s, d in zip(src, dst, strict=True)}


def mpjpe_failures(
    scene: Scene,
    results: PipelineResults,
    *,
    gate_mm: float = MATCH_GATE_MM,
    level: float = RELATIVE_LEVEL,
) -> list[Failure]:
    """Per frame, match the filtered tracks to ground truth (Hungarian on MPJPE, as
    :func:`pipeline.evaluate.evaluate` does); list every matched (frame, track) whose
    MPJPE is at least ``level`` times the run's median MPJPE (score = that ratio), with
    its worst joint. A ground-truth person or a track left unmatched is one entry per
    run of frames, scored as ``gate_mm`` / median (above any matched pair)."""
    if scene.gt is None or results.num_tracks == 0:
        return []
    gt_slots, _ = ground_truth_slots(scene.gt, results.joint_set)
    gt_dense, gt_ids = _frames_of_gt(scene.gt, gt_slots, results.num_frames)  # (F, G, 24, 3)
    pred = to_smpl_slots(results.track_filtered, results.joint_set)  # (K, F, 24, 3)
    slot_joint = _slot_to_joint(results.joint_set)
    slots = np.array(sorted(slot_joint))
    names = _joint_names(results)
    matched, unmatched = [], []
    for f in range(results.num_frames):
        p, g = pred[:, f], gt_dense[f]
        p_ok = np.isfinite(p).all(-1).any(-1)
        g_ok = np.isfinite(g).all(-1).any(-1)
        pairs = metrics.match_people(p, g, max_mpjpe=gate_mm) if p_ok.any() and g_ok.any() else []
        for k, gi in pairs:
            err = metrics.joint_errors(p[k], g[gi])  # (24,) mm
            e = err[slots]
            if np.isfinite(e).any():
                matched.append((f, int(k), int(gi), float(np.nanmean(err)), e))
        matched_p = {k for k, _ in pairs}
        matched_g = {gi for _, gi in pairs}
        for gi in np.flatnonzero(g_ok):
            if int(gi) not in matched_g:
                unmatched.append((f, None, int(gi)))
        for k in np.flatnonzero(p_ok):
            if int(k) not in matched_p:
                unmatched.append((f, int(k), None))
    usual = float(usual_level(np.array([m[3] for m in matched] or [np.nan]), floor=10.0))
    out = []
    for f, k, gi, score, e in matched:
        if score < level * usual:
            continue
        j = slot_joint[int(slots[np.nanargmax(e)])]
        detail = (
            f"MPJPE {score:.0f} mm, {score / usual:.1f}× the run's {usual:.0f} mm "
            f"(worst joint {np.nanmax(e):.0f} mm, GT {gt_ids[gi]})"
        )
        out.append(
            Failure(
                "mpjpe", score / usual, f, k, j, None, where_label(k, names[j]), detail,
                kind="MPJPE", value=score,
            )
        )  # fmt: skip
    for f, k, gi in unmatched:
        if k is None:
            where, detail, kind = "", f"GT person {gt_ids[gi]} matched by no track", "no track"
        else:
            where, detail, kind = where_label(k), "matches no GT person", "no GT"
        # one problem per GT person (or track): the kind and the person make the key
        out.append(
            Failure(
                "mpjpe", gate_mm / usual, f, k, None, None, where, detail,
                kind=kind if gi is None else f"{kind}|{gt_ids[gi]}", value=gate_mm,
            )
        )  # fmt: skip
    return out


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of the runs of True in a 1D bool array."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist(), strict=True))


def association_failures(
    scene: Scene,
    results: PipelineResults,
    *,
    affinity_threshold: float = AFFINITY_THRESHOLD,
    unassigned_confidence: float = UNASSIGNED_CONFIDENCE,
) -> list[Failure]:
    """Association conflicts and gaps (kinds in quotes).

    1. "close to two": a detection of person p whose affinity to a detection of another
       person p' of the frame is ``>= affinity_threshold``; per (frame, p, p'), naming
       the more doubtful detection (the one whose mean affinity to its own person's
       detections is lower); score = that affinity.
    2. "one view": a person triangulated from fewer than 2 views (score 1).
    3. "missing in raw": a track present before and after but missing from the raw
       triangulation: one entry per gap (score 1 + gap length / clip length).
    4. "unassigned": an unassigned detection with mean joint confidence
       ``>= unassigned_confidence`` (score = that confidence), per frame and camera.
    """
    out: list[Failure] = []
    cams, det_person = scene.rig.names, results.det_person
    view = scene.detections.view
    ptrack = results.person_track

    def who(q: int) -> str:
        k = int(ptrack[q])
        return f"track {k}" if k >= 0 else "an untracked person"

    # 1. conflicts, from the affinity edges of each frame
    a, b, aff = results.edge_a, results.edge_b, results.edge_affinity
    pa = det_person[a] if len(a) else np.zeros(0, int)
    pb = det_person[b] if len(b) else np.zeros(0, int)
    same = (pa >= 0) & (pa == pb)
    own_sum = np.zeros(len(det_person))
    own_n = np.zeros(len(det_person))
    np.add.at(own_sum, a[same], aff[same])
    np.add.at(own_sum, b[same], aff[same])
    np.add.at(own_n, a[same], 1)
    np.add.at(own_n, b[same], 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        own = np.where(own_n > 0, own_sum / np.maximum(own_n, 1), np.nan)
    own_rank = np.where(np.isfinite(own), own, -np.inf)  # no own affinity: most doubtful
    worst: dict[tuple[int, int], tuple[float, int, int]] = {}
    for e in np.flatnonzero((pa >= 0) & (pb >= 0) & (pa != pb) & (aff >= affinity_threshold)):
        da, db = int(a[e]), int(b[e])
        d, other = (da, db) if own_rank[da] <= own_rank[db] else (db, da)
        key = (min(pa[e], pb[e]), max(pa[e], pb[e]))
        if key not in worst or aff[e] > worst[key][0]:
            worst[key] = (float(aff[e]), d, other)
    for score, d, other in worst.values():
        q, q2 = int(det_person[d]), int(det_person[other])
        f = int(results.person_frame[q])
        own_txt = f", own {own[d]:.2f}" if np.isfinite(own[d]) else ""
        detail = f"close to {who(q2)} too (affinity {score:.2f}{own_txt})"
        k = _track_or_none(ptrack[q])
        out.append(
            Failure(
                "association", score, f, k, None, int(view[d]),
                where_label(k, None, cams[int(view[d])]), detail,
                kind=f"close to two|{who(q2)}", value=score,
            )
        )  # fmt: skip

    # 2. people seen by fewer than two views
    nviews = (results.person_members >= 0).sum(1)
    for q in np.flatnonzero(nviews < 2):
        f, k = int(results.person_frame[q]), _track_or_none(ptrack[q])
        v = int(np.flatnonzero(results.person_members[q] >= 0)[0]) if nviews[q] else None
        detail = f"seen by {nviews[q]} view" + ("s" if nviews[q] != 1 else "")
        where = where_label(k, None, None if v is None else cams[v])
        out.append(
            Failure("association", 1.0, f, k, None, v, where, detail, kind="one view", value=1)
        )

    # 3. gaps in a track's raw triangulation
    pres = present(results)
    F = max(results.num_frames, 1)
    for k in range(results.num_tracks):
        seen = np.flatnonzero(pres[k])
        if len(seen) < 2:
            continue
        inside = np.zeros(results.num_frames, bool)
        inside[seen[0] : seen[-1] + 1] = True
        for start, stop in _runs(inside & ~pres[k]):
            n = stop - start
            out.append(
                Failure(
                    "association", 1.0 + n / F, start, k, None, None, where_label(k),
                    "missing in raw", kind="missing in raw", first=start, last=stop - 1,
                    frames=n, value=n,
                )
            )  # fmt: skip

    # 4. confident detections nobody took, per frame and camera
    conf = results.det_joints2d[..., 2]
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mean_conf = np.nanmean(np.where(np.isfinite(conf), conf, np.nan), axis=1)
    frames = scene.detections.frame
    best: dict[tuple[int, int], int] = {}
    for d in np.flatnonzero((det_person < 0) & (mean_conf >= unassigned_confidence)):
        key = (int(frames[d]), int(view[d]))
        if key not in best or mean_conf[d] > mean_conf[best[key]]:
            best[key] = int(d)
    for (f, v), d in best.items():
        detail = f"unassigned detection (confidence {mean_conf[d]:.2f})"
        out.append(
            Failure(
                "association", float(mean_conf[d]), f, None, None, v,
                where_label(None, None, cams[v]), detail, kind="unassigned",
                value=float(mean_conf[d]),
            )
        )  # fmt: skip
    return out


def id_failures(scene: Scene, results: PipelineResults) -> list[Failure]:
    """Track births after the first frame and deaths before the last (score 1 to 2,
    higher for shorter tracks), and ID switches of :func:`pipeline.evaluate.evaluate`
    when the scene has ground truth (score :data:`SWITCH_SCORE`)."""
    F = results.num_frames
    pres = present(results)
    out = []
    for k in range(results.num_tracks):
        seen = np.flatnonzero(pres[k])
        if len(seen) == 0:
            continue
        first, last = int(seen[0]), int(seen[-1])
        score = 1.0 + (1.0 - (last - first + 1) / F)
        life = f"lives f {first}–{last}"
        if first > 0:
            out.append(
                Failure("id", score, first, k, None, None, where_label(k), f"born ({life})",
                        kind="birth")
            )  # fmt: skip
        if last < F - 1:
            out.append(
                Failure("id", score, last, k, None, None, where_label(k), f"last seen ({life})",
                        kind="death")
            )  # fmt: skip
    if scene.gt is not None and results.num_tracks:
        for f, gt_id, old, new in evaluate(scene, results).id_switch_events:
            detail = f"ID switch: GT {gt_id} was track {old}"
            out.append(
                Failure("id", SWITCH_SCORE, f, new, None, None, where_label(new), detail,
                        kind="ID switch")
            )  # fmt: skip
    return out


def kalman_failures(
    scene: Scene, results: PipelineResults, *, threshold: float = MAHALANOBIS_THRESHOLD
) -> list[Failure]:
    """Per (frame, track) whose worst joint's Mahalanobis distance exceeds ``threshold``:
    that joint, scored by the distance (already relative: the innovation over its
    expected spread)."""
    del scene
    m = np.where(np.isfinite(results.track_mahalanobis), results.track_mahalanobis, -np.inf)
    if m.size == 0:
        return []
    j_best = m.argmax(-1)  # (K, F)
    worst = np.take_along_axis(m, j_best[..., None], -1)[..., 0]
    names = _joint_names(results)
    out = []
    for k, f in zip(*np.nonzero(worst > threshold), strict=True):
        j, s = int(j_best[k, f]), float(worst[k, f])
        out.append(
            Failure(
                "kalman", s, int(f), int(k), j, None, where_label(int(k), names[j]),
                f"Mahalanobis {s:.1f}", kind="Mahalanobis", value=s,
            )
        )  # fmt: skip
    return out  # a span merges whichever joint is worst frame by frame: MERGE_IGNORES


def smpl_failures(
    scene: Scene,
    results: PipelineResults,
    *,
    tol_deg: float = pose_limits.DEFAULT_TOL_DEG,
    level: float = RELATIVE_LEVEL,
) -> list[Failure]:
    """The VAE-corrected fit if present, else step I: each (frame, track, joint) whose fit
    residual is at least ``level`` times that joint's usual residual (median over the
    run, at least :data:`RESIDUAL_FLOOR_MM`; score = the ratio), and each joint rotation
    outside its limits by more than ``tol_deg`` (score excess / :data:`LIMIT_SCALE_DEG`)."""
    del scene
    fit = results.smpl_vae if results.smpl_vae is not None else results.smpl
    if fit is None:
        return []
    names = _joint_names(results)
    index = {n: i for i, n in enumerate(names)}
    fit_names = get_joint_set(fit.joint_set).names
    out = []
    res = np.asarray(fit.residual, float)  # (K, F, T) mm
    if res.size:
        K, F, T = res.shape
        usual = usual_level(res.reshape(K * F, T), 0, floor=RESIDUAL_FLOOR_MM)  # (T,)
        with np.errstate(invalid="ignore"):
            hits = np.argwhere(res >= level * usual)
        for k, f, t in hits:
            name, r = fit_names[t], float(res[k, f, t])
            detail = f"{fit.stage} residual {r:.0f} mm, {r / usual[t]:.1f}× its usual"
            out.append(
                Failure(
                    "smpl", r / usual[t], int(f), int(k), index.get(name), None,
                    where_label(int(k), name), detail, kind=f"residual|{name}", value=r,
                )
            )  # fmt: skip
    with np.errstate(invalid="ignore"):
        excess = pose_limits.limit_excess(fit.pose_rotvecs)  # (K, F, 24) deg
        excess = np.where(np.isfinite(excess), excess, 0.0)
    if excess.size:
        angles = np.rad2deg(pose_limits.swing_twist(fit.pose_rotvecs))
        for k, f, j in np.argwhere(excess > tol_deg):
            name = SMPL24.names[j]
            detail = _limit_detail(name, angles[k, f, j], float(excess[k, f, j]))
            out.append(
                Failure(
                    "smpl", float(excess[k, f, j]) / LIMIT_SCALE_DEG, int(f), int(k),
                    index.get(name), None, where_label(int(k), name), detail,
                    kind=f"joint limit|{name}", value=float(excess[k, f, j]),
                )
            )  # fmt: skip
    # kinds carry the joint: a joint the results' set lacks (index None) still merges
    # with itself only
    return out


def label_failures(scene: Scene, results: PipelineResults) -> list[Failure]:
    """One entry per finding of :func:`pipeline.label_check.check_results` (raw tracks,
    and each camera's associated 2D against the triangulation), spanning the frames that
    show it, naming its track (None for the scene) and camera; score = measured value /
    threshold (threshold / value for a ratio below its lower bound)."""
    cams = scene.rig.names
    out = []
    for f in check_results(results, scene.rig).findings:
        frame = f.frames[0] if f.frames else 0
        low = f.kind == "proportion" and f.value < f.threshold
        score = f.threshold / f.value if low and f.value > 0 else f.value / f.threshold
        named = f.track is not None or f.camera is not None  # where_label() names them
        detail = f.message.split(": ", 1)[1] if named else f.message
        detail += f" ({len(f.frames)} frames)"
        view = None if f.camera is None else cams[f.camera]
        out.append(
            Failure(
                "labels", float(score), frame, f.track, None, f.camera,
                where_label(f.track, None, view), detail, kind=f.kind,
                value=float(f.value),
            )
        )  # fmt: skip
    return out


def _limit_detail(name: str, angles_deg: np.ndarray, excess_deg: float) -> str:
    """E.g. ``"flexion −143° outside [0°, 150°] (143° over)"`` for the worst axis."""
    lim = pose_limits.LIMITS[name.replace("right_", "left_", 1)]
    over = np.maximum(angles_deg - lim.high, 0.0) + np.maximum(np.array(lim.low) - angles_deg, 0)
    a = int(np.argmax(over))
    return (
        f"{lim.names[a]} {angles_deg[a]:.0f}° outside [{lim.low[a]}°, {lim.high[a]}°] "
        f"({excess_deg:.0f}° over)"
    )


# --------------------------------------------------------------------------- jumps


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


@dataclass(frozen=True)
class Note:
    """A researcher's note on a frame; ``created`` is ISO 8601 local time with offset."""

    frame: int
    text: str
    created: str


def new_note(frame: int, text: str) -> Note:
    return Note(int(frame), str(text), datetime.now().astimezone().isoformat(timespec="seconds"))


def notes_path(scene_root: str | os.PathLike) -> Path:
    """Where a scene's notes live: ``SCENE/.mvviz/notes.json`` (beside the results)."""
    return Path(scene_root) / ".mvviz" / "notes.json"


def load_notes(path: str | os.PathLike) -> list[Note]:
    """The notes in ``path`` (none if it does not exist). A file that is not valid notes
    JSON raises :class:`~pipeline.files.SceneFormatError` naming it and the bad field."""
    path = Path(path)
    if not path.exists():
        return []
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SceneFormatError(path, None, f"not a readable notes file ({exc})") from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("notes"), list):
        raise SceneFormatError(path, "notes", "expected an object with a list 'notes'")
    if doc.get("version") != NOTES_VERSION:
        raise SceneFormatError(path, "version", f"expected {NOTES_VERSION}")
    notes = []
    for i, n in enumerate(doc["notes"]):
        where = f"notes[{i}]"
        if not isinstance(n, dict):
            raise SceneFormatError(path, where, "expected an object")
        frame, text, created = n.get("frame"), n.get("text"), n.get("created")
        if not isinstance(frame, int) or isinstance(frame, bool) or frame < 0:
            raise SceneFormatError(path, f"{where}.frame", f"expected a frame >= 0, got {frame!r}")
        if not isinstance(text, str):
            raise SceneFormatError(path, f"{where}.text", "expected a string")
        if not isinstance(created, str):
            raise SceneFormatError(path, f"{where}.created", "expected an ISO time string")
        try:
            datetime.fromisoformat(created)
        except ValueError:
            raise SceneFormatError(
                path, f"{where}.created", f"not an ISO time: {created!r}"
            ) from None
        notes.append(Note(frame, text, created))
    return notes


def save_notes(path: str | os.PathLike, notes: list[Note]) -> None:
    """Write ``notes`` to ``path`` atomically (a failed write leaves the old file)."""
    doc = {"version": NOTES_VERSION, "notes": [asdict(n) for n in notes]}
    with atomic_write(path, "w") as fh:
        json.dump(doc, fh, indent=2, ensure_ascii=False)
        fh.write("\n")
