"""The association's settings, in one frozen dataclass every association module reads.

Units: mm.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class AssociationParams:
    max_distance_mm: float = 250.0
    """Mean ray-to-ray distance at which affinity reaches zero."""
    joint_clip_mm: float = 500.0
    """Per-joint distance clip: a single wrong joint cannot dominate."""
    min_affinity: float = 0.3
    """Average-linkage threshold for merging clusters."""
    min_confidence: float = 0.1
    min_shared_joints: int = 3
    min_views: int = 2
    prune_mm: float = 300.0
    """Pairs whose distance over body-part mean rays (a cheap screen,
    :func:`pipeline.association.affinity.screened_distances`) is at least this skip the per-joint
    distance and keep the screen's; inf computes every pair."""
    resolve_flips: bool = True
    """Score every pair also with one detection mirrored left/right, and un-mirror the
    detections a cluster finds mirrored (needs the joint set)."""
    merge_distance_mm: float = 200.0
    """Two clusters with no view in common whose triangulated bodies (median joint) are
    closer than this are one person, split because one of its detections disagrees with
    the others (a detection that straddles two people, or has left and right swapped):
    two people cannot stand in one place. They are merged, and triangulation's outlier
    rejection sorts out the joints. 0 disables."""
    split_inconsistent: bool = True
    """Split a cluster whose detections' centre rays do not meet at one body
    (:func:`pipeline.association.refine.split_inconsistent`): affinities are pairwise, and when each
    of two far-apart people is seen by two or three cameras of one height, every cross pair can meet
    somewhere (a different phantom for each pair) while the five rays meet nowhere."""
    refine: bool = True
    """After the greedy linkage, move single detections to the cluster they agree with
    most (:func:`pipeline.association.refine.refine_clusters`). On rings whose cameras stand at one
    height, two people far away can pair up across two views better than either pairs with its own
    person's other views (their epipolar lines are near horizontal); the greedy merge
    takes that pair first and the cannot-link keeps it apart for good."""
