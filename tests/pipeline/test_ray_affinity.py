"""The association's kernels (pipeline.association.affinity) against the loops they replace."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from bench.reference_association import (
    average_linkage_reference,
    pair_ray_distances_unchunked,
    ray_distances_reference,
    screen_distances_unblocked,
)
from pipeline.association.affinity import (
    average_linkage,
    pair_ray_distances,
    part_groups,
    pinhole_rays,
    ray_distances,
    screen_distances,
    screened_distances,
)
from pipeline.association.pairs import shared_joints
from pipeline.association.params import AssociationParams
from pipeline.data.cameras import CameraRig
from pipeline.data.scene import load_scene

REPO = Path(__file__).resolve().parents[2]


def _detections(rng, n_people=6, n_views=8, J=17):
    """Rays of n_people bodies seen from n_views cameras, 2% joints missing, and a
    few rays aimed at nobody; (origins, dirs, weights, views)."""
    cams = rng.normal(0, 1, (n_views, 3)) * [4000, 4000, 500] + [0, 0, 1500]
    bodies = rng.uniform(-2000, 2000, (n_people, 1, 3)) + rng.normal(0, 250, (n_people, J, 3))
    views = np.repeat(np.arange(n_views), n_people)
    person = np.tile(np.arange(n_people), n_views)
    target = bodies[person] + rng.normal(0, 30, (len(views), J, 3))
    target[::7] = rng.uniform(-3000, 3000, (len(target[::7]), J, 3))
    dirs = target - cams[views][:, None]
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    weights = rng.uniform(0.2, 1.0, dirs.shape[:2])
    gone = rng.uniform(size=weights.shape) < 0.02
    dirs[gone], weights[gone] = np.nan, 0.0
    return cams[views], dirs, weights, views


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ray_distances_equal_the_reference(seed):
    o, d, w, views = _detections(np.random.default_rng(seed))
    p = AssociationParams()
    fast, ref = ray_distances(o, d, w, p), ray_distances_reference(o, d, w, p)
    np.testing.assert_array_equal(np.isnan(fast), np.isnan(ref))
    np.testing.assert_allclose(fast, ref, atol=1e-6, equal_nan=True)
    assert (ref[np.isfinite(ref)] < 100).mean() > 0.05  # there are true pairs to find
    half = len(o) // 2  # the two-argument form
    part = ray_distances(o[:half], d[:half], w[:half], p, other=(o[half:], d[half:], w[half:]))
    np.testing.assert_allclose(part, ref[:half, half:], atol=1e-6, equal_nan=True)


@pytest.mark.parametrize("seed", range(6))
def test_average_linkage_equals_the_loop(seed):
    o, d, w, views = _detections(np.random.default_rng(seed), n_people=5, n_views=6)
    p = AssociationParams()
    aff = 1.0 - ray_distances(o, d, w, p) / p.max_distance_mm
    aff[views[:, None] == views[None]] = np.nan
    for threshold in (0.1, 0.3, 0.6):
        ref = average_linkage_reference(aff, views, threshold)
        np.testing.assert_array_equal(average_linkage(aff, views, threshold), ref)
    labels = average_linkage(aff, views, 0.3)
    for c in np.unique(labels):  # cannot-links hold
        assert len(set(views[labels == c])) == (labels == c).sum()
    assert len(np.unique(labels)) < len(labels)  # something merged


def test_linkage_of_one_and_none():
    assert average_linkage(np.full((1, 1), np.nan), np.array([0]), 0.3).tolist() == [0]
    assert average_linkage(np.zeros((0, 0)), np.zeros(0, int), 0.3).shape == (0,)


@pytest.mark.parametrize("seed", [0, 1])
def test_pair_kernel_equals_the_dense_one(seed):
    o, d, w, views = _detections(np.random.default_rng(seed))
    p = AssociationParams()
    dense = ray_distances(o, d, w, p)
    ia, ib = np.triu_indices(len(o), 1)
    flip = np.arange(17).reshape(-1, 1)[::-1].ravel()  # any permutation will do
    straight, mirrored = pair_ray_distances(o, d, w, ia, ib, p, flip=flip)
    np.testing.assert_array_equal(np.isnan(straight), np.isnan(dense[ia, ib]))
    np.testing.assert_allclose(straight, dense[ia, ib], atol=0.05, equal_nan=True)  # float32
    want = ray_distances(o, d, w, p, other=(o, d[:, flip], w[:, flip]))[ia, ib]
    np.testing.assert_allclose(mirrored, want, atol=0.05, equal_nan=True)


def test_blocked_pair_kernel_equals_the_unchunked_one(monkeypatch):
    import pipeline.association.pairs as ray_pairs

    o, d, w, views = _detections(np.random.default_rng(4), n_people=8, n_views=10)
    o[views == 3] = o[views == 2][0]  # two views from one camera centre: the clip
    d[5, 2:], w[5, 2:] = np.nan, 0.0  # too few joints: NaN
    p = AssociationParams()
    ia, ib = np.triu_indices(len(o), 1)
    flip = np.arange(17)[::-1]
    monkeypatch.setattr(ray_pairs, "BLOCK_PAIRS", 700)  # several blocks, a short last one
    for f in (None, flip):
        new, new_m = pair_ray_distances(o, d, w, ia, ib, p, flip=f)
        old, old_m = pair_ray_distances_unchunked(o, d, w, ia, ib, p, flip=f)
        assert len(ia) > 3 * 700 and np.isnan(old).any()
        assert np.isclose(old, p.joint_clip_mm).any() and (old < 100).sum() > 50
        np.testing.assert_array_equal(np.isnan(new), np.isnan(old))
        np.testing.assert_allclose(new, old, atol=1e-3, equal_nan=True)
        if f is None:
            assert new_m is None and old_m is None
        else:
            np.testing.assert_allclose(new_m, old_m, atol=1e-3, equal_nan=True)


def test_blocked_screen_equals_the_unblocked_one(monkeypatch):
    import pipeline.association.pairs as ray_pairs

    o, d, w, views = _detections(np.random.default_rng(5), n_people=8, n_views=10)
    d[7], w[7] = np.nan, 0.0  # no part at all: NaN
    groups = part_groups(np.arange(17)[::-1], 17)
    monkeypatch.setattr(ray_pairs, "SCREEN_BLOCK", 16 * len(o) // 3)  # 16 rows, 5 blocks
    new = screen_distances(o, d, w, groups, 500.0)
    old = screen_distances_unblocked(o, d, w, groups, 500.0)
    off = ~np.eye(len(o), dtype=bool)
    np.testing.assert_array_equal(np.isnan(new)[off], np.isnan(old)[off])
    assert np.isnan(old[7]).all() and (old[off] < 100).sum() > 50
    np.testing.assert_allclose(new[off], old[off], atol=0.01, equal_nan=True)
    np.testing.assert_array_equal(new, new.T)


@pytest.mark.slow
def test_screen_keeps_every_close_pair_and_unpruned_equals_dense():
    o, d, w, views = _detections(np.random.default_rng(3), n_people=8, n_views=10)
    p = AssociationParams()
    dense = ray_distances(o, d, w, p)
    dense[views[:, None] == views[None]] = np.nan
    everything, _ = screened_distances(o, d, w, views, None, replace(p, prune_mm=np.inf))
    np.testing.assert_allclose(everything, dense, atol=0.05, equal_nan=True)
    screen = screen_distances(o, d, w, part_groups(None, 17), p.joint_clip_mm)
    close = dense < p.max_distance_mm  # pairs that can merge
    assert close.sum() > 50 and (screen[close] < p.prune_mm).all()  # none thrown away
    pruned, _ = screened_distances(o, d, w, views, None, p)
    far = np.isfinite(dense) & (screen >= p.prune_mm)
    assert far.mean() > 0.3  # the screen does throw pairs away
    np.testing.assert_allclose(pruned[far], screen[far], atol=0.05)  # float32 screen
    np.testing.assert_allclose(pruned[~far], dense[~far], atol=0.05, equal_nan=True)


def test_part_groups_hold_both_joints_of_a_pair_and_shared_joints_count():
    flip = np.array([0, 2, 1, 4, 3, 5, 7, 6])
    groups = part_groups(flip, 8, parts=3)
    assert sorted(np.concatenate(groups).tolist()) == list(range(8))
    for g in groups:
        assert set(flip[g].tolist()) == set(g.tolist())
    seen = np.random.default_rng(0).uniform(size=(30, 40)) < 0.6
    want = seen.astype(int) @ seen.T.astype(int)
    np.testing.assert_array_equal(shared_joints(seen), want)
    np.testing.assert_array_equal(shared_joints(np.tile(seen, (1, 2))), 2 * want)  # > 64


def test_pinhole_rays_equal_the_cameras_own_and_leave_distorted_views_to_them():
    rig = load_scene(REPO / "sample_data" / "shelf_synth").rig
    rig = CameraRig(cameras=(replace(rig[0], dist=np.array([0.1, 0, 0, 0, 0])), *rig.cameras[1:]))
    rng = np.random.default_rng(0)
    views = rng.integers(0, len(rig), 40)
    px = rng.uniform(100, 700, (40, 17, 2))
    px[3, 2] = np.nan
    rays, plain = pinhole_rays(rig, views, px)
    np.testing.assert_array_equal(plain, views != 0)
    assert np.isnan(rays[~plain]).all() and np.isnan(rays[3, 2]).all()
    for i in np.flatnonzero(plain):
        np.testing.assert_allclose(rays[i], rig[int(views[i])].pixels_to_rays(px[i]), atol=1e-12)
