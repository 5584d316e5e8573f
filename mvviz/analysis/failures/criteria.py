"""One finder per criterion of :data:`~mvviz.analysis.failures.entries.CRITERIA`: each
returns the unmerged :class:`~mvviz.analysis.failures.entries.Failure` entries of a run
(one per frame, or per span for gaps); :mod:`.review` merges and ranks them."""

from __future__ import annotations

import warnings

import numpy as np

from mvviz.analysis.failures.entries import (
    AFFINITY_THRESHOLD,
    CLOSE_MARGIN,
    LIMIT_SCALE_DEG,
    MAHALANOBIS_THRESHOLD,
    MATCH_GATE_MM,
    MERGE_GAP,
    RELATIVE_LEVEL,
    RESIDUAL_FLOOR_MM,
    SWITCH_SCORE,
    UNASSIGNED_CONFIDENCE,
    USUAL_FLOOR_PX,
    Failure,
    joint_names,
    present,
    track_or_none,
    usual_level,
    where_label,
)
from pipeline.body import pose_limits
from pipeline.core.npy_stream import release_pages
from pipeline.data.joint_sets import SMPL24, get_joint_set, mapping_indices
from pipeline.data.scene import Scene
from pipeline.evaluation import metrics
from pipeline.evaluation.evaluate import evaluate, ground_truth_slots, gt_per_frame, to_smpl_slots
from pipeline.evaluation.label_check import check_results
from pipeline.results.store import PipelineResults
from pipeline.run.frames import row_frames
from pipeline.stages.track import bone_lengths


def reprojection_failures(
    scene: Scene, results: PipelineResults, *, level: float = RELATIVE_LEVEL
) -> list[Failure]:
    """Each (person-frame, joint, view) triangulation used whose reprojection error is at
    least ``level`` times that joint's usual error in that camera (the median over the
    run, at least :data:`USUAL_FLOOR_PX`); score = error / usual. Ranking by the ratio
    keeps a camera that always reprojects at 18 px (far away, blurry) from filling the
    list just under the outlier threshold, while an error twice its usual stands out."""
    if results.person_reproj.shape[0] == 0:
        return []
    usual = _usual_reprojection(results)  # (J, V)
    names, cams = joint_names(results), scene.rig.names
    q, j, v, e = _reprojection_hits(results, usual, level)
    off = set(results.config.disabled_views)
    keep = ~np.isin(v, [i for i, name in enumerate(cams) if name in off])
    q, j, v, e = q[keep], j[keep], v[keep], e[keep]
    frame, track = np.asarray(results.person_frame)[q], np.asarray(results.person_track)[q]
    ratio = e / usual[j, v]
    out = []
    for i, first, last, frames in _merged_runs(frame, track, j, ratio):
        k = track_or_none(track[i])
        detail = f"{e[i]:.1f} px, {ratio[i]:.1f}× its usual {usual[j[i], v[i]]:.1f} px"
        detail += " (untracked person)" if k is None else ""
        span = {} if frames == 1 else {"first": first, "last": last, "frames": frames}
        out.append(
            Failure(
                "reprojection", float(ratio[i]), int(frame[i]), k, int(j[i]), int(v[i]),
                where_label(k, names[j[i]], cams[v[i]]), detail, kind="reprojection",
                value=float(e[i]), **span,
            )
        )  # fmt: skip
    return out


def _merged_runs(frame, track, joint, score, max_gap: int = MERGE_GAP):
    """What :func:`~mvviz.analysis.failures.review.merge_spans` makes of one-frame
    entries grouped by (track, joint), in arrays: per run of frames at most ``max_gap``
    apart, (the worst entry's index: highest score, then earliest frame, then first in
    order; first frame; last frame; distinct frames). A long run has millions of
    reprojection hits (10,000 frames x 31 x 20); a Failure each took minutes and GBs."""
    n = len(frame)
    if n == 0:
        return []
    order = np.lexsort((np.arange(n), frame, joint, track))  # by group, then frame, stably
    f, t, jj = frame[order], track[order], joint[order]
    start = np.ones(n, bool)
    start[1:] = (t[1:] != t[:-1]) | (jj[1:] != jj[:-1]) | (f[1:] - f[:-1] > max_gap + 1)
    run = np.cumsum(start) - 1
    pos = np.arange(n)
    # worst per run: the first of (run, -score, frame, position) in lexicographic order
    best = order[np.lexsort((pos, f, -score[order], run))]
    firsts = np.flatnonzero(start)
    worst = best[firsts]  # runs are contiguous and in order: run r's sorted block begins there
    lasts = np.append(firsts[1:], n) - 1
    distinct = np.ones(n, int)
    distinct[1:] = (f[1:] != f[:-1]) | start[1:]
    frames = np.add.reduceat(distinct, firsts)
    return list(zip(worst.tolist(), f[firsts].tolist(), f[lasts].tolist(), frames.tolist(),
                    strict=True))  # fmt: skip


REPROJ_BLOCK_VALUES = 1 << 23  # person-frame x joint x view values read at once (64 MB)


def _used_reprojection(results: PipelineResults, rows: slice, views: slice) -> np.ndarray:
    """(q, J, v) the reprojection errors of the views used, NaN elsewhere."""
    used = np.asarray(results.person_used[rows, :, views])
    return np.where(used, results.person_reproj[rows, :, views], np.nan)


def _usual_reprojection(results: PipelineResults) -> np.ndarray:
    """(J, V) each joint's usual error in each camera (:func:`usual_level` over the run),
    a few cameras at a time: a long run's (Q, J, V) errors are 850 MB at 10,000 frames x
    31 x 20, and whole-array temporaries of them took GBs. The overall median (for a
    (joint, camera) never used) from a per-column sample would differ, so the columns'
    medians of all values are kept and the overall one is taken where it is needed."""
    Q, J, V = results.person_reproj.shape
    step = max(1, REPROJ_BLOCK_VALUES // max(Q * J, 1))
    med = np.full((J, V), np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns
        for v0 in range(0, V, step):
            med[:, v0 : v0 + step] = np.nanmedian(
                _used_reprojection(results, slice(None), slice(v0, v0 + step)), axis=0
            )
            release_pages(results.person_reproj)
            release_pages(results.person_used)
    if np.isfinite(med).all():
        return np.maximum(med, USUAL_FLOOR_PX)
    return usual_level(_used_reprojection(results, slice(None), slice(None)), 0,
                       floor=USUAL_FLOOR_PX)  # fmt: skip


def _reprojection_hits(
    results: PipelineResults, usual: np.ndarray, level: float
) -> tuple[np.ndarray, ...]:
    """(q, j, v, error) of every used error at least ``level`` x usual, by blocks of rows."""
    Q, J, V = results.person_reproj.shape
    step = max(1, REPROJ_BLOCK_VALUES // max(J * V, 1))
    parts = []
    for q0 in range(0, Q, step):
        reproj = _used_reprojection(results, slice(q0, q0 + step), slice(None))
        with np.errstate(invalid="ignore"):
            q, j, v = np.nonzero(reproj / usual >= level)
        parts.append((q + q0, j, v, reproj[q, j, v]))
        release_pages(results.person_reproj)
        release_pages(results.person_used)
    return tuple(np.concatenate(p) for p in zip(*parts, strict=True))


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
    :func:`pipeline.evaluation.evaluate.evaluate` does); list every matched (frame, track) whose
    MPJPE is at least ``level`` times the run's median MPJPE (score = that ratio), with
    its worst joint. A ground-truth person or a track left unmatched is one entry per
    run of frames, scored as ``gate_mm`` / median (above any matched pair)."""
    if scene.gt is None or results.num_tracks == 0:
        return []
    gt_slots, _ = ground_truth_slots(scene.gt, results.joint_set)
    gt_dense, gt_ids = gt_per_frame(scene.gt, gt_slots, results.num_frames)  # (F, G, 24, 3)
    pred = to_smpl_slots(results.track_filtered, results.joint_set)  # (K, F, 24, 3)
    slot_joint = _slot_to_joint(results.joint_set)
    slots = np.array(sorted(slot_joint))
    names = joint_names(results)
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
    close_margin: float = CLOSE_MARGIN,
) -> list[Failure]:
    """Association conflicts and gaps (kinds in quotes).

    1. "close to two": a detection of person p whose agreement with another person p' of
       its frame (its mean affinity to p''s detections, an incompatible or unknown pair
       counting 0) is ``>= affinity_threshold`` and within ``close_margin`` of its
       agreement with p (the same mean over p's other detections; 0 where p has no
       other): the association could have gone either way. Per (frame, {p, p'}) the
       detection of highest agreement (the lowest row of ties); score = that agreement.
    2. "one view": a person triangulated from fewer than 2 views (score 1).
    3. "missing in raw": a track present before and after but missing from the raw
       triangulation: one entry per gap (score 1 + gap length / clip length).
    4. "unassigned": an unassigned detection with mean joint confidence
       ``>= unassigned_confidence`` (score = that confidence), per frame and camera.
    """
    return [
        *_close_to_two(scene, results, affinity_threshold, close_margin),
        *_one_view(scene, results),
        *_raw_gaps(results),
        *_unassigned(scene, results, unassigned_confidence),
    ]


EDGE_BLOCK = 1 << 22  # edges read at once (~4 M: ~100 MB of temporaries)


def _edge_blocks(results: PipelineResults):
    """(a, b, affinity, person of a, person of b) per block of the affinity edges, the
    maps' pages released after each: at 10,000 frames x 31 x 20 there are ~200 M edges
    (3.3 GB mapped), and whole-array temporaries of them took ~20 GB."""
    det_person, E = results.det_person, len(results.edge_a)
    for i in range(0, E, EDGE_BLOCK):
        a = np.asarray(results.edge_a[i : i + EDGE_BLOCK])
        b = np.asarray(results.edge_b[i : i + EDGE_BLOCK])
        aff = np.asarray(results.edge_affinity[i : i + EDGE_BLOCK])
        yield a, b, aff, det_person[a], det_person[b]
        for arr in (results.edge_a, results.edge_b, results.edge_affinity):
            release_pages(arr)


def _edge_summary(
    results: PipelineResults, affinity_threshold: float
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """One pass over the affinity edges: (D,) each detection's agreement with its own
    person (the mean of its affinities to the person's other detections, a negative or
    unknown one counting 0; NaN where the person has no other), and the (detection,
    other person, agreement) of every agreement with another person of the frame that
    is ``>= affinity_threshold`` (rows by frame, then detection and person). Results
    keep only the compatible pairs across people (affinity > 0), which are the ones
    that count. A frame's edges are contiguous but may straddle two blocks: each block's
    last frame waits for the next. Two passes, one per figure, read the 3.3 GB of edges
    of 10,000 frames x 31 x 20 twice."""
    det_person, person_frame = results.det_person, results.person_frame
    n, Q = len(det_person), len(person_frame)
    size = np.bincount(det_person[det_person >= 0], minlength=Q)  # detections per person
    # each person's frame's first person (people are stored frame by frame; else None:
    # _agreements sorts its keys instead)
    in_order = bool(np.all(person_frame[1:] >= person_frame[:-1]))
    first = np.searchsorted(person_frame, person_frame) if in_order else None
    own_sum = np.zeros(n)
    held = [np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)]
    found: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    for a, b, aff, pa, pb in _edge_blocks(results):
        agree = np.maximum(aff.astype(float), 0.0)
        same = (pa >= 0) & (pa == pb)
        ends = np.concatenate([a[same], b[same]])
        if len(ends):
            # a block's edges are of a few consecutive frames: count over their rows only
            lo = int(ends.min())
            sums = np.bincount(ends - lo, np.tile(agree[same], 2))
            own_sum[lo : lo + len(sums)] += sums
        c = np.flatnonzero((pa >= 0) & (pb >= 0) & ~same & (aff > 0))
        rows = [np.concatenate([h, x]) for h, x in zip(held, (
            np.concatenate([a[c], b[c]]).astype(np.int64),
            np.concatenate([pb[c], pa[c]]).astype(np.int64),
            np.tile(agree[c], 2)), strict=True)]  # fmt: skip
        frame = person_frame[det_person[rows[0]]]
        done = frame < frame.max(initial=-1)  # the last frame may go on in the next block
        held = [r[~done] for r in rows]
        found.append(
            _agreements([r[done] for r in rows], det_person, size, first, affinity_threshold)
        )
    found.append(_agreements(held, det_person, size, first, affinity_threshold))
    with np.errstate(invalid="ignore", divide="ignore"):
        others = size[np.maximum(det_person, 0)] - 1
        own = np.where((det_person >= 0) & (others > 0), own_sum / np.maximum(others, 1), np.nan)
    d, q2, agreement = (np.concatenate(x) for x in zip(*found, strict=True))
    return own, (d, q2, agreement)


def _agreements(rows, det_person: np.ndarray, size: np.ndarray, first: np.ndarray | None,
                threshold: float):  # fmt: skip
    """(detection, other person, agreement >= threshold) from directed cross edges
    (detection, other person, max(affinity, 0)) holding every edge of their frames;
    ``first`` (Q,): the first person of each person's frame (None: people out of frame
    order, the keys sorted instead).
    Summed by one bincount over (detection, the other's place among its frame's people):
    np.unique's sort of (detection, person) keys took ~30 s of a 10,000-frame dome."""
    d, q2, w = rows
    if len(d) == 0:
        return d, q2, w
    if first is None:
        key = d * len(size) + q2
        uniq, inv = np.unique(key, return_inverse=True)
        agreement = np.bincount(inv, w, minlength=len(uniq)) / size[uniq % len(size)]
        hit = agreement >= threshold
        return uniq[hit] // len(size), uniq[hit] % len(size), agreement[hit]
    place = q2 - first[q2]
    width, lo = int(place.max()) + 1, int(d.min())
    sums = np.bincount((d - lo) * width + place, w)
    key = np.flatnonzero(sums > 0)  # every edge kept across people has affinity > 0
    d_hit = key // width + lo
    q_hit = first[det_person[d_hit]] + key % width
    agreement = sums[key] / size[q_hit]
    hit = agreement >= threshold
    return d_hit[hit], q_hit[hit], agreement[hit]


def _close_to_two(
    scene: Scene, results: PipelineResults, affinity_threshold: float, close_margin: float
) -> list[Failure]:
    """1. conflicts, from the affinity edges of each frame."""
    cams, det_person, view = scene.rig.names, results.det_person, scene.detections.view
    ptrack = results.person_track
    size = np.bincount(det_person[det_person >= 0], minlength=len(results.person_frame))

    def who(q: int) -> str:
        k = int(ptrack[q])
        return f"track {k}" if k >= 0 else "an untracked person"

    own, (d, q2, agree) = _edge_summary(results, affinity_threshold)
    own0 = np.nan_to_num(own, nan=0.0)  # alone in its person: any other agreement is close
    near = agree >= own0[d] - close_margin
    d, q2, agree = d[near], q2[near], agree[near]
    q = det_person[d]
    frame = results.person_frame[q]
    lo, hi = np.minimum(q, q2), np.maximum(q, q2)
    # per pair of people of a frame its detection of highest agreement (lowest row of ties)
    order = np.lexsort((d, -agree, hi, lo))
    first = np.ones(len(order), bool)
    first[1:] = (lo[order][1:] != lo[order][:-1]) | (hi[order][1:] != hi[order][:-1])
    w = order[first]
    w = w[np.lexsort((d[w], frame[w]))]  # the pairs in frame order, then by detection
    d, q, q2, agree, frame = d[w], q[w], q2[w], agree[w], frame[w]
    k, k2 = ptrack[q], ptrack[q2]
    v = np.asarray(view)[d]
    # merge_spans' problems (kind: the other person's name; track; camera) as one int key,
    # their runs in arrays: a long dome run had ~2 M such entries and a Failure each took
    # ~20 s; only the merged entries are made (merge_spans leaves them as they are)
    other_key = np.maximum(k2, -1) + 1  # 0: an untracked person
    key = v.astype(np.int64) * (int(other_key.max(initial=0)) + 1) + other_key
    runs = _merged_runs(frame, np.maximum(k, -1), key, agree)
    if not runs:
        return []
    # merge_spans' order: problems as they first appear, then their runs by frame
    problem = (np.maximum(k, -1) + 1).astype(np.int64) * (int(key.max()) + 1) + key
    _, first_seen, which = np.unique(problem, return_index=True, return_inverse=True)
    rank = np.argsort(np.argsort(first_seen))  # each problem's place by first appearance
    runs.sort(key=lambda r: (rank[which[r[0]]], r[1]))
    out = []
    for e, first_f, last_f, frames in runs:
        score, de, other = float(agree[e]), int(d[e]), int(q2[e])
        own_txt = f", own {own[de]:.2f}" if np.isfinite(own[de]) else ", alone in its person"
        detail = (f"close to {who(other)} too (mean affinity {score:.2f} to its "
                  f"{size[other]} detections{own_txt})")  # fmt: skip
        kt = track_or_none(k[e])
        out.append(
            Failure(
                "association", score, int(frame[e]), kt, None, int(v[e]),
                where_label(kt, None, cams[int(v[e])]), detail,
                kind=f"close to two|{who(other)}", value=score,
                first=first_f, last=last_f, frames=frames,
            )
        )  # fmt: skip
    return out


def _one_view(scene: Scene, results: PipelineResults) -> list[Failure]:
    """2. people seen by fewer than two views."""
    cams, out = scene.rig.names, []
    nviews = (results.person_members >= 0).sum(1)
    for q in np.flatnonzero(nviews < 2):
        f, k = int(results.person_frame[q]), track_or_none(results.person_track[q])
        v = int(np.flatnonzero(results.person_members[q] >= 0)[0]) if nviews[q] else None
        detail = f"seen by {nviews[q]} view" + ("s" if nviews[q] != 1 else "")
        where = where_label(k, None, None if v is None else cams[v])
        out.append(
            Failure("association", 1.0, f, k, None, v, where, detail, kind="one view", value=1)
        )
    return out


def _raw_gaps(results: PipelineResults) -> list[Failure]:
    """3. gaps in a track's raw triangulation."""
    pres = present(results)
    F = max(results.num_frames, 1)
    out = []
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
    return out


def _unassigned(
    scene: Scene, results: PipelineResults, unassigned_confidence: float
) -> list[Failure]:
    """4. confident detections nobody took, per frame and camera."""
    cams, view = scene.rig.names, scene.detections.view
    # only the unassigned rows' joints are read (a long run's are mapped, 1.9 GB at
    # 10,000 frames x 31 x 20; those rows are a few per frame)
    rows = np.flatnonzero(np.asarray(results.det_person) < 0)
    conf = np.asarray(results.det_joints2d[rows, :, 2])
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mean_conf = np.full(len(results.det_person), np.nan)
        mean_conf[rows] = np.nanmean(np.where(np.isfinite(conf), conf, np.nan), axis=1)
    release_pages(results.det_joints2d)
    frames = row_frames(scene, results.config)  # where the stages used it (sync.offsets)
    best: dict[tuple[int, int], int] = {}
    for d in rows[mean_conf[rows] >= unassigned_confidence]:
        key = (int(frames[d]), int(view[d]))
        if key not in best or mean_conf[d] > mean_conf[best[key]]:
            best[key] = int(d)
    out = []
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
    higher for shorter tracks), and ID switches of :func:`pipeline.evaluation.evaluate.evaluate`
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
    names = joint_names(results)
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


def proportion_failures(scene: Scene, results: PipelineResults) -> list[Failure]:
    """Each (frame, track, joint) the proportion check (:mod:`pipeline.stages.proportions`)
    re-solved or found contradicting its track's bones, scored by how far the frame's
    triangulation put the joint's worst bone from the track's median length (relative,
    over the check's tolerance: 1 = at the limit)."""
    del scene
    resolved, contradicted = results.track_resolved, results.track_contradicted
    if resolved is None or contradicted is None or not (resolved | contradicted).any():
        return []
    bones = np.array(get_joint_set(results.joint_set).bones).reshape(-1, 2)
    tolerance = results.config.proportions.tolerance
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a bone no frame of a track has
        median = np.nanmedian(bone_lengths(results.track_raw, bones), axis=1)  # (K, B)
    person_of = {
        (int(k), int(f)): q
        for q, (k, f) in enumerate(zip(results.person_track, results.person_frame, strict=True))
        if k >= 0
    }
    names = joint_names(results)
    out = []
    for k, f, j in zip(*np.nonzero(resolved | contradicted), strict=True):
        k, f, j = int(k), int(f), int(j)
        q = person_of.get((k, f))
        measured = results.person_joints[q] if q is not None else results.track_raw[k, f]
        mine = (bones == j).any(1)
        with np.errstate(invalid="ignore", divide="ignore"):
            dev = np.abs(bone_lengths(measured, bones[mine]) / median[k, mine] - 1.0)
        worst = float(np.nanmax(dev)) if np.isfinite(dev).any() else tolerance
        moved = float(np.linalg.norm(measured[j] - results.track_raw[k, f, j]))
        if contradicted[k, f, j]:
            kind, detail = "contradicted", f"a bone {100 * worst:.0f} % off; not filtered"
        else:
            kind = "re-solved"
            detail = f"a bone {100 * worst:.0f} % off; moved {moved:.0f} mm by other views"
        out.append(
            Failure(
                "proportions", worst / tolerance, f, k, j, None, where_label(k, names[j]),
                detail, kind=kind, value=worst,
            )
        )  # fmt: skip
    return out


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
    names = joint_names(results)
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
    if fit.prior_reverted is not None:
        limit = results.config.smpl_fit.max_extra_residual_mm
        for k, f in np.argwhere(fit.prior_reverted):
            detail = (
                f"the prior's correction cost more than {limit:g} mm of residual: "
                "step I's pose kept"
            )
            out.append(
                Failure(
                    "smpl", 1.0, int(f), int(k), None, None, where_label(int(k)), detail,
                    kind="prior backed off", value=1.0,
                )
            )  # fmt: skip
    # kinds carry the joint: a joint the results' set lacks (index None) still merges
    # with itself only
    return out


def label_failures(scene: Scene, results: PipelineResults) -> list[Failure]:
    """One entry per finding of :func:`pipeline.evaluation.label_check.check_results` (raw tracks,
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
