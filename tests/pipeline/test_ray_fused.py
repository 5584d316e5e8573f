"""The compiled screen and kernel (pipeline.association.fused) against the NumPy path it replaces
on big frames (pipeline.association.affinity.screened_distances with COMPILED_MIN_DETECTIONS out
of reach)."""

from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np
import pytest

import pipeline.association.affinity as ray_affinity
from bench.reference_association import average_linkage_reference, fused_pairwise_distances
from pipeline.association.affinity import (
    average_linkage,
    linkage_distances_reference,
    part_groups,
    ray_distances,
    screen_distances,
)
from pipeline.association.fused import fused_screened_distances, linkage_distances
from pipeline.association.params import AssociationParams
from tests.pipeline.test_ray_affinity import _detections

FLIP = np.array([0, 2, 1, 4, 3, 6, 5, 8, 7, 10, 9, 12, 11, 14, 13, 16, 15])  # COCO-17's


def _both(monkeypatch, o, d, w, views, flip, p):
    """(compiled, NumPy) screened_distances of one frame."""
    monkeypatch.setattr(ray_affinity, "COMPILED_MIN_DETECTIONS", 0)
    fused = ray_affinity.screened_distances(o, d, w, views, flip, p)
    monkeypatch.setattr(ray_affinity, "COMPILED_MIN_DETECTIONS", sys.maxsize)
    numpy = ray_affinity.screened_distances(o, d, w, views, flip, p)
    return fused, numpy


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fused_equals_the_numpy_screen_and_kernel(monkeypatch, seed):
    o, d, w, views = _detections(np.random.default_rng(seed), n_people=10, n_views=12)
    o[views == 3] = o[views == 2][0]  # two views from one camera centre: the clip
    d[5, 2:], w[5, 2:] = np.nan, 0.0  # too few joints: NaN
    d[9], w[9] = np.nan, 0.0  # nothing seen
    p = AssociationParams()
    (dist, mirrored), (want, want_m) = _both(monkeypatch, o, d, w, views, FLIP, p)
    for got, ref in ((dist, want), (mirrored, want_m)):
        assert got.shape == ref.shape == (len(o), len(o))
        np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
        # NumPy's float32 is off by up to ~0.6 mm where a joint's rays are near parallel
        # (the float64 kernel matches the dense float64 distance: the test below)
        err = np.abs(got - ref)[np.isfinite(ref)]
        assert np.median(err) < 1e-3 and np.mean(err < 0.02) > 0.999 and err.max() < 1.0
    # the cases the comparison is about are all there
    near = np.isfinite(mirrored)
    assert near.sum() > 100 and (np.isfinite(dist) & ~near).sum() > 100  # kept and pruned
    assert np.isclose(dist, p.joint_clip_mm).any() and (dist < 50).sum() > 100
    assert np.isnan(dist[9]).all() and np.isnan(np.diag(dist)).all()
    assert np.isnan(dist[views[:, None] == views[None]]).all()


def test_fused_kernel_equals_the_float64_dense_distance_on_the_pairs_it_keeps():
    o, d, w, views = _detections(np.random.default_rng(7), n_people=8, n_views=10)
    p = AssociationParams()
    groups = part_groups(FLIP, 17)
    dist, mirrored = fused_screened_distances(o, d, w, views, FLIP, groups, p)
    dense = ray_distances(o, d, w, p)
    dense_m = ray_distances(o, d, w, p, other=(o, d[:, FLIP], w[:, FLIP]))
    kept = np.isfinite(mirrored)
    assert kept.sum() > 100
    np.testing.assert_allclose(dist[kept], dense[kept], atol=1e-6)  # both float64
    np.testing.assert_allclose(mirrored[kept], dense_m[kept], atol=1e-6)
    pruned = np.isfinite(dist) & ~kept  # the screen's own distance, at or past prune_mm
    screen = screen_distances(o, d, w, groups, p.joint_clip_mm)
    assert (dist[pruned] >= p.prune_mm).all()
    np.testing.assert_allclose(dist[pruned], screen[pruned], atol=0.05)  # float32 screen


def test_fused_without_a_flip_and_on_tiny_frames(monkeypatch):
    o, d, w, views = _detections(np.random.default_rng(3), n_people=5, n_views=10)
    p = AssociationParams()
    (dist, mirrored), (want, _) = _both(monkeypatch, o, d, w, views, None, p)
    assert np.isnan(mirrored).all()
    np.testing.assert_allclose(dist, want, atol=0.05, equal_nan=True)
    everything = replace(p, prune_mm=np.inf)  # no screen: every pair's kernel
    (dist, _), (want, _) = _both(monkeypatch, o, d, w, views, None, everything)
    np.testing.assert_allclose(dist, want, atol=0.05, equal_nan=True)
    monkeypatch.setattr(ray_affinity, "COMPILED_MIN_DETECTIONS", 0)
    for n in (0, 1):
        dist, mirrored = ray_affinity.screened_distances(o[:n], d[:n], w[:n], views[:n], FLIP, p)
        assert dist.shape == mirrored.shape == (n, n) and np.isnan(dist).all()


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_rows_of_pairs_equal_one_pair_at_a_time_to_the_bit(seed):
    """The vectorised pass (a row of kept pairs per detection, every joint's term added
    with selects) against the scalar pass one pair at a time with a branch per joint: the
    same numbers, bit for bit, straight and mirrored, with and without a flip and a
    screen, on frames with every case the branches decide."""
    rng = np.random.default_rng(seed)
    o, d, w, views = _detections(rng, n_people=9, n_views=11)
    o[views == 3] = o[views == 2][0]  # two views from one camera centre: the clip
    d[5, 2:], w[5, 2:] = np.nan, 0.0  # too few joints: NaN
    d[9], w[9] = np.nan, 0.0  # nothing seen
    w[rng.uniform(size=w.shape) < 0.05] = 0.0  # seen with no weight
    # parallel rays (no term): a joint of one detection along another's from elsewhere
    a, b = np.flatnonzero(views == 0)[0], np.flatnonzero(views == 1)[0]
    d[b, :4] = d[a, :4]
    n = len(o)
    for flip, p in (
        (FLIP, AssociationParams()),
        (None, AssociationParams()),
        (FLIP, AssociationParams(prune_mm=np.inf, min_shared_joints=5)),
    ):
        groups = part_groups(flip, 17)
        rows = fused_screened_distances(o, d, w, views, flip, groups, p)
        pairs = fused_pairwise_distances(o, d, w, views, flip, groups, p)
        for got, want in zip(rows, pairs, strict=True):
            assert got.shape == want.shape == (n, n)
            np.testing.assert_array_equal(got, want)  # NaN where NaN; the same floats
            assert np.array_equal(got, got.T, equal_nan=True)
        assert np.isfinite(rows[0]).sum() > n * n / 3 and (rows[0] < 50).sum() > 100
        if flip is not None:  # mirrored: scored, and another number than straight
            scored = np.isfinite(rows[1])
            assert scored.sum() > 100 and (rows[1][scored] != rows[0][scored]).mean() > 0.8


@pytest.mark.parametrize("seed", [0, 1])
def test_compiled_linkage_distances_equal_numpys_and_cluster_as_the_loop(seed):
    """pipeline.association.fused.linkage_distances against the NumPy steps it replaces, to the
    bit (unknown affinities, same-view pairs, an affinity matrix not quite symmetric),
    and average_linkage on a frame big enough to take it against the greedy loop."""
    o, d, w, views = _detections(np.random.default_rng(seed), n_people=6, n_views=9)
    p = AssociationParams()
    assert len(views) >= ray_affinity.COMPILED_MIN_DETECTIONS
    aff = 1.0 - ray_distances(o, d, w, p) / p.max_distance_mm
    aff[views[:, None] == views[None]] = np.nan
    lopsided = aff * (1.0 + 1e-12 * np.random.default_rng(seed).normal(size=aff.shape))
    for a in (aff, lopsided):
        got = linkage_distances(a, views.astype(np.int64))
        want = linkage_distances_reference(a, views)
        assert got.shape == (len(views) * (len(views) - 1) // 2,)
        np.testing.assert_array_equal(got, want)
    assert (want > 1e3).sum() > 100 and (want == 1.0).sum() + (want < 0.7).sum() > 100
    for threshold in (0.1, 0.3, 0.6):
        ref = average_linkage_reference(aff, views, threshold)
        np.testing.assert_array_equal(average_linkage(aff, views, threshold), ref)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_compiled_frame_affinity_equals_numpys_steps(monkeypatch, seed):
    """pipeline.association.fused.frame_affinity (one pass: the better distance, the affinity and
    the linkage's condensed distances) against np.fmin, the affinity formula and
    linkage_distances_reference, to the bit, on a frame's real screened distances (NaN on
    the diagonal and for same-view pairs, mirrored NaN where the screen pruned) with
    NaNs on one side only and ties; and the clusters it gives the linkage."""
    o, d, w, views = _detections(np.random.default_rng(seed), n_people=8, n_views=10)
    p = AssociationParams()
    dist, mirrored = ray_affinity.screened_distances(o, d, w, views, FLIP, p)
    mirrored = mirrored.copy()
    tie = np.isfinite(dist) & np.isfinite(mirrored)
    tie &= np.random.default_rng(seed).random(tie.shape) < 0.1
    mirrored[tie | tie.T] = dist[tie | tie.T]
    assert np.isnan(mirrored).sum() > np.isnan(dist).sum() > len(views)  # one-sided NaNs
    monkeypatch.setattr(ray_affinity, "COMPILED_MIN_DETECTIONS", 0)
    best, aff, condensed = ray_affinity.frame_affinity(dist, mirrored, views, p.max_distance_mm)
    monkeypatch.setattr(ray_affinity, "COMPILED_MIN_DETECTIONS", sys.maxsize)
    best_np, aff_np, none = ray_affinity.frame_affinity(dist, mirrored, views, p.max_distance_mm)
    assert none is None
    np.testing.assert_array_equal(best, best_np)
    np.testing.assert_array_equal(aff, aff_np)
    np.testing.assert_array_equal(condensed, linkage_distances_reference(aff_np, views))
    assert (best < dist).sum() > 50 and np.isfinite(aff).mean() > 0.5
    for threshold in (0.1, 0.3, 0.6):
        got = average_linkage(aff, views, threshold, condensed=condensed)
        np.testing.assert_array_equal(got, average_linkage(aff_np, views, threshold))
