"""Failure review: rank what went wrong in a run, worst first, and keep notes on frames.

Pure functions over a :class:`~pipeline.data.scene.Scene` and its
:class:`~pipeline.results.store.PipelineResults`; the GUI is :mod:`mvviz.panels.failure_panel`.
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
``proportions``           (track, joint) re-solved from other views, or kept     bone off /
                          but not filtered, for contradicting the track's      tolerance
                          bone lengths
``smpl``                  (track, joint) with a fit residual >= 2x that       see below
                          joint's usual; rotation outside its
                          ``pose_limits.LIMITS`` box; person-frames where
                          the prior's correction backed off (kept step I)
``labels``                finding of :mod:`pipeline.evaluation.label_check` (scene,      measured /
                          track or camera)                                     threshold
========================  ==================================================  ===========

Scores rank entries within one criterion; relative scores (a ratio to the usual level)
keep a camera or joint that is always a bit off from filling a list just under a limit.
``association``: the affinity of a detection to another person's detections (0.5..1),
1 + gap / clip length for a track gap, 1.0 for a one-view person, the mean joint
confidence of an unassigned detection. ``id``: 3 for an ID switch, 1 to 2 for a birth or
death (shorter-lived tracks higher). ``smpl``: residual / usual, or degrees outside the
limits / 10 deg, or 1 where the prior backed off. ``labels``: how far the measure is
past its threshold (2 = twice the allowed fraction; a ratio below its lower bound scores
bound / ratio).

Notes (:class:`Note`) are JSON beside the results: ``SCENE/.mvviz/notes.json``.
Units: millimetres and pixels, as in the results.

Layout: :mod:`.entries` (the :class:`Failure` entry, its labels and the thresholds),
:mod:`.criteria` (one finder per criterion), :mod:`.review` (merging, ranking and
counting entries, the camera to show), :mod:`.notes`. Import the public names from
this package.
"""

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
    LIMIT_SCALE_DEG,
    MAHALANOBIS_THRESHOLD,
    MATCH_GATE_MM,
    MERGE_GAP,
    MERGE_IGNORES,
    RELATIVE_LEVEL,
    RESIDUAL_FLOOR_MM,
    SWITCH_SCORE,
    UNASSIGNED_CONFIDENCE,
    USUAL_FLOOR_PX,
    Failure,
    camera_label,
    label,
    present,
    usual_level,
    where_label,
)
from mvviz.analysis.failures.notes import (
    NOTES_VERSION,
    Note,
    load_notes,
    new_note,
    notes_path,
    save_notes,
)
from mvviz.analysis.failures.review import (
    all_failures,
    available_criteria,
    disabled_views,
    find_failures,
    kind_counts,
    merge_spans,
    nearest_pose,
    rank,
    seeing_view,
)

__all__ = [
    "AFFINITY_THRESHOLD",
    "CRITERIA",
    "LIMIT_SCALE_DEG",
    "MAHALANOBIS_THRESHOLD",
    "MATCH_GATE_MM",
    "MERGE_GAP",
    "MERGE_IGNORES",
    "NOTES_VERSION",
    "RELATIVE_LEVEL",
    "RESIDUAL_FLOOR_MM",
    "SWITCH_SCORE",
    "UNASSIGNED_CONFIDENCE",
    "USUAL_FLOOR_PX",
    "Failure",
    "Note",
    "all_failures",
    "association_failures",
    "available_criteria",
    "camera_label",
    "disabled_views",
    "find_failures",
    "id_failures",
    "kalman_failures",
    "proportion_failures",
    "kind_counts",
    "label",
    "label_failures",
    "load_notes",
    "merge_spans",
    "mpjpe_failures",
    "nearest_pose",
    "new_note",
    "notes_path",
    "present",
    "rank",
    "reprojection_failures",
    "save_notes",
    "seeing_view",
    "smpl_failures",
    "usual_level",
    "where_label",
]
