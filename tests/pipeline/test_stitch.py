"""Offline track stitching (pipeline/stages/stitch.py): a person split by the association
or reborn after a gap becomes one track; people who are apart, or who differ in body
proportions, stay apart."""

from __future__ import annotations

import numpy as np

from pipeline.stages.stitch import StitchParams, stitch_tracks
from pipeline.stages.track import TrackingParams, track_people, tracks_from_labels

# a 6-joint chain: its 5 bones are the body's proportions
BONES = np.array([(0, 1), (1, 2), (2, 3), (3, 4), (4, 5)])


def body(x: float, y: float, scale: float = 1.0) -> np.ndarray:
    """(6, 3) a vertical chain of joints 300 mm apart (times ``scale``) at (x, y), mm."""
    z = np.arange(6) * 300.0 * scale
    return np.column_stack([np.full(6, x), np.full(6, y), z])


def rows_of(*people: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(frames (Q,), joints (Q, 6, 3)) of people given as (frames, (len, 6, 3) poses)."""
    frames = np.concatenate([f for f, _ in people])
    joints = np.concatenate([p for _, p in people])
    order = np.argsort(frames, kind="stable")
    return frames[order], joints[order]


def walk(frames: np.ndarray, start: tuple[float, float], step=(20.0, 0.0), scale=1.0):
    return frames, np.stack([body(start[0] + step[0] * i, start[1] + step[1] * i, scale)
                             for i in range(len(frames))])  # fmt: skip


def test_a_person_reborn_after_a_gap_is_one_track():
    # seen 0-39, unseen 40-89 (longer than the tracker waits), seen again 90-149
    a = walk(np.arange(40), (0, 0))
    b = walk(np.arange(90, 150), (0 + 20 * 90, 0))
    other = walk(np.arange(150), (0, 3000))  # someone else all along, 3 m away
    frames, joints = rows_of(a, b, other)
    params = TrackingParams(max_gap=12, reid_max_gap=0)
    tracks = track_people(frames, joints, 150, params, bones=BONES)
    assert tracks.num_tracks == 3  # the online tracker splits the first person
    labels = stitch_tracks(tracks.track_of, frames, joints, bones=BONES)
    assert len(np.unique(labels)) == 2 and (labels >= 0).all()
    first = labels[frames < 40][joints[frames < 40][:, 0, 1] < 1000]
    later = labels[frames >= 90][joints[frames >= 90][:, 0, 1] < 1000]
    assert np.unique(first).tolist() == np.unique(later).tolist()
    merged = tracks_from_labels(labels, frames, joints, 150)
    assert merged.num_tracks == 2
    assert (merged.first_frame == 0).all() and (merged.last_frame == 149).all()


def test_a_second_cluster_beside_a_person_is_absorbed():
    person = walk(np.arange(100), (0, 0))
    dup_frames = np.arange(30, 36)
    dup = dup_frames, person[1][dup_frames] + [60.0, 0, 0]  # 6 cm off, for 6 frames
    frames, joints = rows_of(person, dup)
    labels = np.zeros(len(frames), int)
    is_dup = np.zeros(len(frames), bool)
    is_dup[np.flatnonzero(np.isin(frames, dup_frames))[1::2]] = True
    labels[is_dup] = 1
    out = stitch_tracks(labels, frames, joints, bones=BONES)
    assert set(out[~is_dup]) == {0}
    assert (out[is_dup] == -1).all() or (out[is_dup] == 0).all()
    # one row per frame per track
    kept = out >= 0
    assert len(np.unique(frames[kept])) == kept.sum()


def test_people_who_stay_apart_or_differ_are_not_joined():
    # two people side by side for the whole run, 400 mm apart (not the same body)
    a = walk(np.arange(80), (0, 0))
    b = walk(np.arange(80), (0, 400))
    frames, joints = rows_of(a, b)
    labels = (joints[:, 0, 1] > 200).astype(int)
    assert len(np.unique(stitch_tracks(labels, frames, joints, bones=BONES))) == 2
    # one leaves, a taller one enters where they left: different proportions
    a = walk(np.arange(50), (0, 0))
    b = walk(np.arange(60, 120), (20 * 50, 0), scale=1.2)
    frames, joints = rows_of(a, b)
    labels = (frames >= 60).astype(int)
    assert len(np.unique(stitch_tracks(labels, frames, joints, bones=BONES))) == 2
    # the same proportions but 5 m from where the first left, 10 frames later
    b = walk(np.arange(60, 120), (20 * 50 + 5000, 0))
    frames, joints = rows_of(a, b)
    assert len(np.unique(stitch_tracks(labels, frames, joints, bones=BONES))) == 2
    # disabled: nothing changes
    b = walk(np.arange(60, 120), (20 * 50, 0))
    frames, joints = rows_of(a, b)
    off = stitch_tracks(labels, frames, joints, bones=BONES, params=StitchParams(enabled=False))
    np.testing.assert_array_equal(off, labels)
    assert len(np.unique(stitch_tracks(labels, frames, joints, bones=BONES))) == 1
