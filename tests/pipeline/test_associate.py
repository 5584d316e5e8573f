"""Cross-view association on the real Shelf rig."""

from __future__ import annotations

import numpy as np

from pipeline.association.associate import associate_frame
from pipeline.association.params import AssociationParams
from tests.pipeline.helpers import observe, shelf_rig, standing_people

# Floor spots inside the Shelf rig's shared view, as in the Shelf dataset.
SPOTS = np.array([[0.0, 0.0], [900.0, -700.0], [-600.0, 600.0], [1200.0, 500.0]])


def _clusters_match_truth(assoc, person) -> bool:
    for c in range(assoc.num_people):
        members = person[assoc.cluster == c]
        if len(set(members.tolist())) != 1:
            return False
    # Every person seen in >= 2 views forms exactly one cluster.
    for p in np.unique(person):
        if (person == p).sum() >= 2 and len(set(assoc.cluster[person == p].tolist())) != 1:
            return False
    return True


def test_four_people_are_grouped_exactly():
    rig = shelf_rig()
    joints = standing_people(SPOTS, np.array([0.3, 2.0, -1.0, 3.0]))
    views, kp, person = observe(rig, joints, sigma_px=2.0)
    a = associate_frame(rig, views, kp)
    assert a.num_people == len(np.unique(person))
    assert _clusters_match_truth(a, person)
    # No person holds two detections of one view (the cannot-link constraint).
    for c in range(a.num_people):
        v = views[a.cluster == c]
        assert len(v) == len(set(v.tolist()))
    # Affinity is symmetric, NaN within a view, high for true pairs, low for false.
    assert np.allclose(a.affinity, a.affinity.T, equal_nan=True)
    same = person[:, None] == person[None, :]
    diffview = views[:, None] != views[None, :]
    assert np.nanmin(a.affinity[same & diffview]) > 0.6
    # A wrong pair can look right to two cameras (both on one epipolar line): that
    # is why clusters must agree across all views. Typical wrong pairs score low.
    assert np.nanmedian(a.affinity[~same & diffview]) < 0.0


def test_people_standing_close_stay_apart():
    rig = shelf_rig()
    joints = standing_people(np.array([[0.0, 0.0], [650.0, 0.0]]), np.array([0.0, np.pi]), seed=2)
    views, kp, person = observe(rig, joints, sigma_px=2.5, seed=2)
    a = associate_frame(rig, views, kp)
    assert a.num_people == 2 and _clusters_match_truth(a, person)


def test_false_positive_in_one_view_is_left_unassigned():
    rig = shelf_rig()
    joints = standing_people(SPOTS[:2], np.array([0.0, 1.0]))
    views, kp, person = observe(rig, joints)
    ghost_3d = standing_people(np.array([[-1500.0, -1500.0]]), np.array([0.5]), seed=7)
    ghost = np.concatenate([rig[2].project(ghost_3d)[0], np.full((24, 1), 0.4)], 1)
    views = np.append(views, 2)
    kp = np.concatenate([kp, ghost[None]])
    a = associate_frame(rig, views, kp)
    assert a.cluster[-1] == -1
    assert _clusters_match_truth(a, np.append(person, 99)) and a.num_people == 2


def test_one_view_people_and_disabled_views():
    rig = shelf_rig()
    joints = standing_people(SPOTS[:1], np.array([0.0]))
    views, kp, person = observe(rig, joints)
    assert len(views) >= 3
    only = views == views[0]
    a = associate_frame(rig, views[only], kp[only])
    assert a.num_people == 0 and (a.cluster == -1).all()
    enabled = np.ones(len(rig), bool)
    enabled[views[0]] = False
    a = associate_frame(rig, views, kp, enabled_views=enabled)
    assert a.num_people == 1 and a.cluster[0] == -1 and (a.cluster[1:] == 0).all()


def test_empty_and_nan_frames():
    rig = shelf_rig()
    a = associate_frame(rig, np.zeros(0, int), np.zeros((0, 17, 3)))
    assert a.num_people == 0 and a.members.shape == (0, 5)
    kp = np.full((3, 17, 3), np.nan)
    kp[..., 2] = 0
    a = associate_frame(rig, np.array([0, 1, 2]), kp)
    assert a.num_people == 0 and (a.cluster == -1).all()


def test_threshold_controls_merging():
    rig = shelf_rig()
    joints = standing_people(SPOTS[:2], np.array([0.0, 1.0]))
    views, kp, _ = observe(rig, joints, sigma_px=2.0)
    strict = associate_frame(rig, views, kp, AssociationParams(min_affinity=0.999))
    assert strict.num_people == 0  # nothing agrees that perfectly with 2 px noise


def _mirror(kp: np.ndarray, rows) -> np.ndarray:
    from pipeline.data.joint_sets import SMPL24

    kp = kp.copy()
    kp[rows] = kp[rows][:, SMPL24.flip_index]
    return kp


def test_mirrored_detections_are_found_and_unmirrored():
    """A detector that labels a person seen from behind as if from the front swaps every
    left and right joint: the cluster finds which of its detections are mirrored."""
    from pipeline.data.joint_sets import SMPL24
    from pipeline.stages.triangulate import triangulate_people

    rig = shelf_rig()
    joints = standing_people(SPOTS[:3], np.array([0.3, 2.0, -1.0]))
    views, kp, person = observe(rig, joints, sigma_px=2.0)
    # Person 0 mirrored in two of its views, person 1 in one.
    bad = np.concatenate([np.flatnonzero(person == 0)[:2], np.flatnonzero(person == 1)[:1]])
    mirrored = _mirror(kp, bad)
    a = associate_frame(rig, views, mirrored, joint_set=SMPL24)
    assert _clusters_match_truth(a, person)
    np.testing.assert_array_equal(np.flatnonzero(a.flipped), np.sort(bad))
    # Un-mirrored, person 0 triangulates as well as from clean 2D.
    rows = np.flatnonzero(person == 0)
    fixed = mirrored.copy()
    fixed[a.flipped] = fixed[a.flipped][:, SMPL24.flip_index]
    cams = np.full((1, len(rig), 24, 3), np.nan)
    cams[..., 2] = 0.0
    cams[0, views[rows]] = fixed[rows]
    err = np.linalg.norm(triangulate_people(rig, cams).points[0] - joints[0], axis=-1)
    assert np.nanmean(err) < 15.0
    # Without the joint set nothing is mirrored, and the clean people never are.
    assert not associate_frame(rig, views, mirrored).flipped.any()
    assert not associate_frame(rig, views, kp, joint_set=SMPL24).flipped.any()


def test_one_person_split_in_two_clusters_is_merged():
    from pipeline.association.associate import merge_duplicates

    rig = shelf_rig()
    joints = standing_people(np.array([[0.0, 0.0], [700.0, 0.0]]), np.array([0.3, 0.3]))
    views, kp, person = observe(rig, joints, sigma_px=2.0)
    rows0 = np.flatnonzero(person == 0)
    assert len(rows0) >= 4
    # Person 0 split in two clusters (as a straddling or mirrored detection does):
    # one place, one person. Person 1, 700 mm away, stays apart.
    cluster = np.where(person == 0, 0, 10)
    cluster[rows0[len(rows0) // 2 :]] = 1
    from pipeline.association.associate import detection_rays

    rays = detection_rays(rig, views, kp, min_confidence=0.1)
    merged = merge_duplicates(*rays, views, cluster, AssociationParams())
    assert len(set(merged[rows0])) == 1
    assert set(merged[person == 1]) == {10} and merged[rows0[0]] != 10
    off = merge_duplicates(*rays, views, cluster, AssociationParams(merge_distance_mm=0.0))
    np.testing.assert_array_equal(off, cluster)
