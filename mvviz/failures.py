"""Failure review: rank what went wrong in a run, worst first, and keep notes on frames.

Pure functions over a :class:`~pipeline.scene.Scene` and its
:class:`~pipeline.results.PipelineResults`; the GUI is :mod:`mvviz.failure_panel`.
:func:`find_failures` returns :class:`Failure` entries for one criterion, each naming
the frame and, where they apply, the track, the joint (an index into the results' joint
set, ``None`` where that set lacks it) and the view (camera index):

========================  ==================================================  ===========
criterion                 one entry per                                        score
========================  ==================================================  ===========
``reprojection``          (frame, track): worst joint/view among used views   px
``mpjpe``                 (frame, track) matched to ground truth (Hungarian   mm
                          on MPJPE, the filtered tracks); unmatched people
                          score the matching gate
``association``           person pair whose detections look alike, person     see below
                          seen by < 2 views, track gap, confident unassigned
                          detection
``id``                    track birth after frame 0, death before the last,   see below
                          ID switch against ground truth
``kalman``                (frame, track) with a joint's Mahalanobis distance  Mahalanobis
                          above the threshold: its worst joint
``smpl``                  (frame, track): worst SMPL fit residual; joint      severity
                          rotation outside its ``pose_limits.LIMITS`` box
``labels``                finding of :mod:`pipeline.label_check` (scene,      measured /
                          track or camera) at the first frame showing it      threshold
========================  ==================================================  ===========

Scores rank entries within one criterion. ``association``: the affinity of a detection
to another person's detections (0.5..1), 1.0 for a track gap or a one-view person, the
mean joint confidence of an unassigned detection. ``id``: 3 for an ID switch, 1 to 2
for a birth or death (shorter-lived tracks higher). ``smpl``: residual / 50 mm or
degrees outside the limits / 10 deg, so 50 mm off counts like 10 deg too far.
``labels``: how far the measure is past its threshold (2 = twice the allowed fraction;
a ratio below its lower bound scores bound / ratio).

Notes (:class:`Note`) are JSON beside the results: ``SCENE/.mvviz/notes.json``.
Units: millimetres and pixels, as in the results.
"""

from __future__ import annotations

import json
import math
import os
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
RESIDUAL_SCALE_MM = 50.0
LIMIT_SCALE_DEG = 10.0
SWITCH_SCORE = 3.0
NOTES_VERSION = 1


@dataclass(frozen=True)
class Failure:
    """One thing to look at. ``joint`` indexes the results' joint set, ``view`` the rig;
    ``text`` is a one-line label, e.g. ``"f 123 · track 2 · left_wrist · cam 3 · 41.2 px"``."""

    criterion: str
    score: float
    frame: int
    track: int | None
    joint: int | None
    view: int | None
    text: str


def label(
    frame: int,
    track: int | None = None,
    joint: str | None = None,
    view: str | None = None,
    detail: str = "",
) -> str:
    """``"f 12 · track 2 · left_wrist · cam 3 · detail"``, leaving out what is None."""
    parts = [f"f {frame}"]
    if track is not None:
        parts.append(f"track {track}")
    if joint is not None:
        parts.append(joint)
    if view is not None:
        parts.append(f"cam {view}")
    if detail:
        parts.append(detail)
    return " · ".join(parts)


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

    ``mpjpe`` and ID switches need ``scene.gt``, ``smpl`` a fit: without them those
    lists are empty (``id`` still lists births and deaths).
    """
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
    return rank(found, top)


def available_criteria(scene: Scene, results: PipelineResults) -> tuple[str, ...]:
    """The criteria that can find something in this scene and run."""
    out = [c for c in CRITERIA if c != "mpjpe" or scene.gt is not None]
    if results.smpl is None and results.smpl_vae is None:
        out.remove("smpl")
    return tuple(out)


def rank(failures: list[Failure], top: int) -> list[Failure]:
    """Worst first (ties: earlier frame, lower track); NaN scores dropped."""
    ok = [f for f in failures if math.isfinite(f.score)]
    ok.sort(key=lambda f: (-f.score, f.frame, -1 if f.track is None else f.track))
    return ok[: max(int(top), 0)]


# --------------------------------------------------------------------------- criteria


def _track_or_none(track: int) -> int | None:
    return int(track) if track >= 0 else None


def _joint_names(results: PipelineResults) -> tuple[str, ...]:
    return get_joint_set(results.joint_set).names


def present(results: PipelineResults) -> np.ndarray:
    """(K, F) bool: the track has a raw triangulated joint in the frame."""
    return np.isfinite(results.track_raw).all(-1).any(-1)


def reprojection_failures(scene: Scene, results: PipelineResults) -> list[Failure]:
    """Per person-frame (i.e. per (frame, track)) its worst reprojection error, px, over
    the joints and views triangulation used."""
    reproj = np.where(results.person_used, results.person_reproj, np.nan)  # (Q, J, V)
    Q, J, V = reproj.shape
    flat = np.where(np.isfinite(reproj), reproj, -np.inf).reshape(Q, J * V)
    if Q == 0:
        return []
    best = flat.argmax(1)
    worst = flat[np.arange(Q), best]
    names, cams = _joint_names(results), scene.rig.names
    out = []
    for q in np.flatnonzero(np.isfinite(worst)):
        j, v = divmod(int(best[q]), V)
        f, k = int(results.person_frame[q]), _track_or_none(results.person_track[q])
        detail = f"{worst[q]:.1f} px" + (" (untracked person)" if k is None else "")
        text = label(f, k, names[j], cams[v], detail)
        out.append(Failure("reprojection", float(worst[q]), f, k, j, v, text))
    return out


def _slot_to_joint(joint_set: str) -> dict[int, int]:
    """SMPL-24 slot -> index in ``joint_set`` (for the joints both name alike)."""
    js = get_joint_set(joint_set)
    src, dst = mapping_indices(js, SMPL24)
    return {int(d): int(s) for s, d in zip(src, dst, strict=True)}


def mpjpe_failures(
    scene: Scene, results: PipelineResults, *, gate_mm: float = MATCH_GATE_MM
) -> list[Failure]:
    """Per frame, match the filtered tracks to ground truth (Hungarian on MPJPE, as
    :func:`pipeline.evaluate.evaluate` does) and report every matched (frame, track)
    with its MPJPE and worst joint; a ground-truth person or a track left unmatched
    scores ``gate_mm``."""
    if scene.gt is None or results.num_tracks == 0:
        return []
    gt_slots, _ = ground_truth_slots(scene.gt, results.joint_set)
    gt_dense, gt_ids = _frames_of_gt(scene.gt, gt_slots, results.num_frames)  # (F, G, 24, 3)
    pred = to_smpl_slots(results.track_filtered, results.joint_set)  # (K, F, 24, 3)
    slot_joint = _slot_to_joint(results.joint_set)
    slots = np.array(sorted(slot_joint))
    names = _joint_names(results)
    out = []
    for f in range(results.num_frames):
        p, g = pred[:, f], gt_dense[f]
        p_ok = np.isfinite(p).all(-1).any(-1)
        g_ok = np.isfinite(g).all(-1).any(-1)
        pairs = metrics.match_people(p, g, max_mpjpe=gate_mm) if p_ok.any() and g_ok.any() else []
        for k, gi in pairs:
            err = metrics.joint_errors(p[k], g[gi])  # (24,) mm
            e = err[slots]
            if not np.isfinite(e).any():
                continue
            j = slot_joint[int(slots[np.nanargmax(e)])]
            score = float(np.nanmean(err))
            detail = f"MPJPE {score:.0f} mm (worst {np.nanmax(e):.0f} mm, GT {gt_ids[gi]})"
            out.append(Failure("mpjpe", score, f, k, j, None, label(f, k, names[j], None, detail)))
        matched_p = {k for k, _ in pairs}
        matched_g = {gi for _, gi in pairs}
        for gi in np.flatnonzero(g_ok):
            if int(gi) not in matched_g:
                text = label(f, None, None, None, f"GT person {gt_ids[gi]} matched by no track")
                out.append(Failure("mpjpe", gate_mm, f, None, None, None, text))
        for k in np.flatnonzero(p_ok):
            if int(k) not in matched_p:
                text = label(f, int(k), None, None, "matches no GT person")
                out.append(Failure("mpjpe", gate_mm, f, int(k), None, None, text))
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
    """Association conflicts and gaps.

    1. "close to two people": a detection of person p whose affinity to a detection of
       another person p' of the frame is ``>= affinity_threshold``; one entry per
       (frame, p, p'), naming the more doubtful detection (the one whose mean affinity
       to its own person's detections is lower); score = that affinity.
    2. a person triangulated from fewer than 2 views (score 1).
    3. a track present before and after but missing from the raw triangulation: one
       entry per gap, at its first frame (score 1).
    4. an unassigned detection with mean joint confidence ``>= unassigned_confidence``
       (score = that confidence).
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
        text = label(f, k, None, cams[int(view[d])], detail)
        out.append(Failure("association", score, f, k, None, int(view[d]), text))

    # 2. people seen by fewer than two views
    nviews = (results.person_members >= 0).sum(1)
    for q in np.flatnonzero(nviews < 2):
        f, k = int(results.person_frame[q]), _track_or_none(ptrack[q])
        v = int(np.flatnonzero(results.person_members[q] >= 0)[0]) if nviews[q] else None
        detail = f"seen by {nviews[q]} view" + ("s" if nviews[q] != 1 else "")
        text = label(f, k, None, None if v is None else cams[v], detail)
        out.append(Failure("association", 1.0, f, k, None, v, text))

    # 3. gaps in a track's raw triangulation
    pres = present(results)
    for k in range(results.num_tracks):
        seen = np.flatnonzero(pres[k])
        if len(seen) < 2:
            continue
        inside = np.zeros(results.num_frames, bool)
        inside[seen[0] : seen[-1] + 1] = True
        for start, stop in _runs(inside & ~pres[k]):
            n = stop - start
            span = f"{n} frames: f {start}–{stop - 1}" if n > 1 else "1 frame"
            detail = f"missing in raw ({span})"
            text = label(start, k, None, None, detail)
            out.append(Failure("association", 1.0, start, k, None, None, text))

    # 4. confident detections nobody took
    conf = results.det_joints2d[..., 2]
    with np.errstate(invalid="ignore"):
        mean_conf = np.nanmean(np.where(np.isfinite(conf), conf, np.nan), axis=1)
    frames = scene.detections.frame
    for d in np.flatnonzero((det_person < 0) & (mean_conf >= unassigned_confidence)):
        f, v = int(frames[d]), int(view[d])
        detail = f"unassigned detection (confidence {mean_conf[d]:.2f})"
        out.append(
            Failure(
                "association",
                float(mean_conf[d]),
                f,
                None,
                None,
                v,
                label(f, None, None, cams[v], detail),
            )
        )
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
                Failure(
                    "id", score, first, k, None, None, label(first, k, None, None, f"born ({life})")
                )
            )
        if last < F - 1:
            out.append(
                Failure(
                    "id",
                    score,
                    last,
                    k,
                    None,
                    None,
                    label(last, k, None, None, f"last seen ({life})"),
                )
            )
    if scene.gt is not None and results.num_tracks:
        for f, gt_id, old, new in evaluate(scene, results).id_switch_events:
            detail = f"ID switch: GT {gt_id} was track {old}"
            out.append(
                Failure("id", SWITCH_SCORE, f, new, None, None, label(f, new, None, None, detail))
            )
    return out


def kalman_failures(
    scene: Scene, results: PipelineResults, *, threshold: float = MAHALANOBIS_THRESHOLD
) -> list[Failure]:
    """Per (frame, track) whose worst joint's Mahalanobis distance exceeds ``threshold``:
    that joint, scored by the distance."""
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
        text = label(int(f), int(k), names[j], None, f"Mahalanobis {s:.1f}")
        out.append(Failure("kalman", s, int(f), int(k), j, None, text))
    return out


def smpl_failures(
    scene: Scene, results: PipelineResults, *, tol_deg: float = pose_limits.DEFAULT_TOL_DEG
) -> list[Failure]:
    """The VAE-corrected fit if present, else step I: per (frame, track) the worst fit
    residual (score residual / :data:`RESIDUAL_SCALE_MM`) and the joint rotation furthest
    outside its limits by more than ``tol_deg`` (score excess / :data:`LIMIT_SCALE_DEG`)."""
    del scene
    fit = results.smpl_vae if results.smpl_vae is not None else results.smpl
    if fit is None:
        return []
    names = _joint_names(results)
    index = {n: i for i, n in enumerate(names)}
    fit_names = get_joint_set(fit.joint_set).names
    out = []
    res = np.where(np.isfinite(fit.residual), fit.residual, -np.inf)  # (K, F, T) mm
    if res.size:
        t_best = res.argmax(-1)
        worst = np.take_along_axis(res, t_best[..., None], -1)[..., 0]
        for k, f in zip(*np.nonzero(np.isfinite(worst)), strict=True):
            name, r = fit_names[t_best[k, f]], float(worst[k, f])
            text = label(int(f), int(k), name, None, f"{fit.stage} residual {r:.0f} mm")
            out.append(
                Failure("smpl", r / RESIDUAL_SCALE_MM, int(f), int(k), index.get(name), None, text)
            )
    with np.errstate(invalid="ignore"):
        excess = pose_limits.limit_excess(fit.pose_rotvecs)  # (K, F, 24) deg
        excess = np.where(np.isfinite(excess), excess, 0.0)
    if excess.size:
        j_best = excess.argmax(-1)
        worst = np.take_along_axis(excess, j_best[..., None], -1)[..., 0]
        angles = np.rad2deg(pose_limits.swing_twist(fit.pose_rotvecs))
        for k, f in zip(*np.nonzero(worst > tol_deg), strict=True):
            j = int(j_best[k, f])
            name = SMPL24.names[j]
            detail = _limit_detail(name, angles[k, f, j], float(worst[k, f]))
            out.append(
                Failure(
                    "smpl",
                    float(worst[k, f]) / LIMIT_SCALE_DEG,
                    int(f),
                    int(k),
                    index.get(name),
                    None,
                    label(int(f), int(k), name, None, detail),
                )
            )
    return out


def label_failures(scene: Scene, results: PipelineResults) -> list[Failure]:
    """One entry per finding of :func:`pipeline.label_check.check_results` (raw tracks,
    and each camera's associated 2D against the triangulation), at the first frame that
    shows it, naming its track (None for the scene) and camera; score = measured value /
    threshold (threshold / value for a ratio below its lower bound)."""
    cams = scene.rig.names
    out = []
    for f in check_results(results, scene.rig).findings:
        frame = f.frames[0] if f.frames else 0
        low = f.kind == "proportion" and f.value < f.threshold
        score = f.threshold / f.value if low and f.value > 0 else f.value / f.threshold
        named = f.track is not None or f.camera is not None  # label() names them
        detail = f.message.split(": ", 1)[1] if named else f.message
        detail += f" ({len(f.frames)} frames)"
        view = None if f.camera is None else cams[f.camera]
        text = label(frame, f.track, None, view, detail)
        out.append(Failure("labels", float(score), frame, f.track, None, f.camera, text))
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
