"""The association's geometric checks (pipeline/association/refine.py): the fast forms
used every frame against the plain NumPy they replace."""

import numpy as np
import pytest

from pipeline.association.refine import (
    CentreRays,
    _ray_point_distance,
    cluster_centers,
    label_counts,
)


@pytest.mark.parametrize(
    "cluster",
    [
        np.array([3, 3, 0, 7, 0, 3, 12]),
        np.array([5]),
        np.zeros(0, int),
        np.array([-1, 2, -1, 4]),  # negative labels: np.unique itself
        np.arange(40)[::-1],
    ],
)
def test_label_counts_is_np_unique(cluster):
    want = np.unique(cluster, return_inverse=True, return_counts=True)
    got = label_counts(cluster)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)


def _geometry(n: int, seed: int = 0) -> CentreRays:
    rng = np.random.default_rng(seed)
    views = rng.integers(0, 8, n)
    ang = views * (2 * np.pi / 8)
    centres = np.c_[6000 * np.cos(ang), 6000 * np.sin(ang), np.full(n, 2500.0)]  # a ring
    target = rng.normal(0, 1500, (n, 3))
    d = target[:, None] - centres[:, None] + rng.normal(0, 50, (n, 17, 3))
    dirs = d / np.linalg.norm(d, axis=-1, keepdims=True)
    weights = rng.uniform(0.2, 1.0, (n, 17))
    weights[0] = 0.0  # a detection without joints: a zero centre ray
    dirs[1, :5] = np.nan
    return CentreRays.of(centres, dirs, weights)


def test_distances_equal_the_per_point_form_in_front_and_behind():
    geo = _geometry(60)
    rng = np.random.default_rng(1)
    # points in the capture volume, and far behind the cameras (distance to the origin)
    points = np.r_[rng.normal(0, 2000, (12, 3)), rng.normal(0, 1, (3, 3)) + [30000, 0, 0]]
    want = _ray_point_distance(geo.origins, geo.rays, points)
    got = geo.distances(points)
    assert got.shape == (15, 60)
    np.testing.assert_allclose(got, want, atol=1e-6, rtol=1e-9)  # mm
    # the zero ray (no joints) measures to the camera centre
    np.testing.assert_allclose(got[:, 0], np.linalg.norm(points - geo.origins[0], axis=-1))
    assert not geo.has_ray[0] and geo.has_ray[1:].all()


def test_centres_are_the_least_squares_points_of_their_rays():
    geo = _geometry(40, seed=3)
    member = np.zeros((40, 3), bool)
    member[1:10, 0] = member[10:25, 1] = True
    member[0, 2] = member[30, 2] = member[31, 2] = True  # row 0 has no ray: ignored
    got = geo.centres(member)
    for k in range(3):
        rows = np.flatnonzero(member[:, k] & geo.has_ray)
        o, r = geo.origins[rows], geo.rays[rows]
        P = np.eye(3) - r[:, :, None] * r[:, None, :]
        want = np.linalg.solve(P.sum(0), np.einsum("nab,nb->a", P, o))
        np.testing.assert_allclose(got[k], want, atol=1e-6)

        # the least-squares point: the mean squared distance to its rays is minimal there
        def spread(p, o=o, r=r):
            return (_ray_point_distance(o, r, p) ** 2).mean()

        for step in np.eye(3) * 5.0:
            assert spread(got[k]) <= min(spread(got[k] + step), spread(got[k] - step))


def test_cluster_centers_are_nan_for_fewer_than_two_rays():
    geo = _geometry(30, seed=5)
    cluster = np.zeros(30, int)
    cluster[1:12], cluster[12:], cluster[0] = 1, 2, 3  # row 0 has no ray: label 3 none
    cluster[29] = 4  # one ray only
    got = cluster_centers(geo.origins, None, None, cluster, [1, 2, 3, 4], geometry=geo)
    assert np.isfinite(got[:2]).all() and np.isnan(got[2:]).all()
    member = np.stack([cluster == k for k in (1, 2)], 1)
    np.testing.assert_array_equal(got[:2], geo.centres(member))


def _move_state(rng, n: int, C: int, V: int, geometric: bool):
    """A refinement's state: (n, C) gains (ties on purpose: quantised), cluster columns
    with their (C, V) view counts and sizes, (C, n) centre distances, rays."""
    col = rng.integers(0, C, n)
    views = rng.integers(0, V, n)
    seen = np.zeros((C, V), np.int64)
    np.add.at(seen, (col, views), 1)
    size = np.bincount(col, minlength=C).astype(np.int64)
    gain = np.round(rng.normal(0.0, 1.0, (n, C)), 1)  # many exact ties
    dist = rng.uniform(0, 400, (C, n)) if geometric else np.zeros((0, 0))
    has_ray = rng.random(n) > 0.1
    return gain, col, seen, views, size, dist, has_ray


@pytest.mark.slow
@pytest.mark.parametrize("geometric", [False, True])
def test_compiled_best_move_is_numpys(geometric):
    """pipeline.association.fused.best_move against the NumPy step it replaces on big frames:
    the same (detection, cluster, gain) on random states with ties, with and without the
    centre-ray test, and with min_views making some moves strand their clusters."""
    from pipeline.association.fused import best_move
    from pipeline.association.refine import _best_move

    rng = np.random.default_rng(7)
    kinds = set()
    for trial in range(300):
        n, C = int(rng.integers(2, 80)), int(rng.integers(1, 12))
        state = _move_state(rng, n, C, int(rng.integers(1, 9)), geometric)
        for min_views in (1, 2, 3):
            want = _best_move(*state, 200.0, min_views)
            got = best_move(*state, 200.0, min_views)
            assert got[:2] == want[:2] and got[2] == want[2], (trial, min_views)
            kinds.add(want[2] > 1e-9)
    assert kinds == {True, False}  # moves and no move both seen


@pytest.mark.slow
def test_refine_takes_the_same_moves_compiled_and_not(monkeypatch):
    """refine_clusters on a frame big enough for the compiled move, both ways: the same
    labels after real moves (clusters cut in halves and misplaced detections)."""
    import pipeline.association.affinity as ray_affinity
    from pipeline.association.params import AssociationParams
    from pipeline.association.refine import refine_clusters
    from tests.pipeline.test_ray_affinity import _detections

    rng = np.random.default_rng(3)
    o, d, w, views = _detections(rng, n_people=8, n_views=10)
    p = AssociationParams()
    aff = 1.0 - ray_affinity.ray_distances(o, d, w, p) / p.max_distance_mm
    aff[views[:, None] == views[None]] = np.nan
    start = ray_affinity.average_linkage(aff, views, p.min_affinity)
    noisy = start.copy()
    pick = rng.choice(len(views), len(views) // 4, replace=False)
    noisy[pick] = rng.choice(np.unique(start), len(pick))  # misplaced detections
    geo = CentreRays.of(o, d, w)
    for cluster in (start, noisy):
        out = {}
        for name, low in (("compiled", 0), ("numpy", 10**9)):
            monkeypatch.setattr(ray_affinity, "COMPILED_MIN_DETECTIONS", low)
            out[name] = refine_clusters(aff, views, cluster.copy(), p.min_affinity,
                                        geometry=geo, max_mm=p.joint_clip_mm)  # fmt: skip
        np.testing.assert_array_equal(out["compiled"], out["numpy"])
    assert (out["numpy"] != noisy).sum() >= 5  # it moved detections
