"""Tests of pipeline.stages.triangulate: weighted DLT and the per-person stage with outlier
rejection.

Units: world millimetres, pixels. Noise-free round trips must come back to 1e-6 mm; noisy
ones are judged against the first-order (linearised) error of the view geometry.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.data.cameras import Camera, CameraRig, make_camera
from pipeline.importers.calibration import read_voxelpose_calibration
from pipeline.stages.triangulate import Triangulation, triangulate_dlt, triangulate_people
from tests.conftest import REPO

SHELF = REPO / "sample_data" / "rigs" / "shelf_voxelpose.json"


# --------------------------------------------------------------------------- helpers


def look_at_camera(
    name: str, center: np.ndarray, *, focal: float, roll: float = 0.0, dist=(0, 0, 0, 0, 0)
) -> Camera:
    """A 1000 x 800 camera at ``center`` (mm) looking at the world origin, z up."""
    forward = -center / np.linalg.norm(center)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = np.cos(roll), np.sin(roll)
    R = np.stack([c * right + s * down, -s * right + c * down, forward])
    K = [[focal, 0, 500.0], [0, focal * 1.02, 400.0], [0, 0, 1]]
    return make_camera(
        name=name, width=1000, height=800, K=K, dist=dist, R=R, t=-R @ center
    )  # fmt: skip


def keypoints_of(rig: CameraRig, points: np.ndarray, conf: float = 1.0) -> np.ndarray:
    """(P, J, 3) world mm -> (P, V, J, 3) exact distorted pixels + confidence."""
    uv = np.moveaxis(rig.project(points), 0, 1)  # (P, V, J, 2)
    return np.concatenate([uv, np.full(uv.shape[:-1] + (1,), conf)], axis=-1)


def normalised_of(rig: CameraRig, keypoints: np.ndarray) -> np.ndarray:
    """(P, V, J, 3) -> (P, J, V, 2) undistorted normalised coordinates."""
    xy = np.stack(
        [cam.undistort_to_normalised(keypoints[:, v, :, :2]) for v, cam in enumerate(rig)],
        axis=2,
    )  # (P, J, V, 2)
    return xy


def rt_matrices(rig: CameraRig) -> np.ndarray:
    return np.stack([np.hstack([c.R, c.t[:, None]]) for c in rig])


@pytest.fixture(scope="module")
def shelf() -> CameraRig:
    return read_voxelpose_calibration(SHELF)


def shelf_points(rig: CameraRig, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) points in the Shelf capture volume (0-1.8 m high) inside all five images."""
    centre = rig.centers[:, :2].mean(0)
    out = []
    while sum(len(o) for o in out) < n:
        X = np.column_stack(
            [rng.uniform(-1500, 1500, (4 * n, 2)) + centre, rng.uniform(0, 1800, 4 * n)]
        )
        uv = rig.project(X)
        size = np.array([[c.width, c.height] for c in rig])[:, None]
        out.append(X[((uv > 0) & (uv < size)).all(-1).all(0)])
    return np.concatenate(out)[:n]


def first_order_mean_error(rig: CameraRig, X: np.ndarray, sigma_px: float, rng) -> np.ndarray:
    """(n,) expected |error| of the maximum-likelihood point under isotropic pixel noise.

    Linearised: covariance sigma^2 (J^T J)^-1 with J the (2 V, 3) Jacobian of the
    projections (central differences); E|e| of that Gaussian by Monte Carlo.
    """
    eps = 1e-3
    steps = np.eye(3) * eps
    jac = np.stack(
        [(rig.project(X + d) - rig.project(X - d)) / (2 * eps) for d in steps], axis=-1
    )  # (V, n, 2, 3)
    jac = np.moveaxis(jac, 0, 1).reshape(len(X), -1, 3)
    cov = sigma_px**2 * np.linalg.inv(np.swapaxes(jac, 1, 2) @ jac)
    samples = np.linalg.cholesky(cov)[:, None] @ rng.normal(size=(len(X), 2000, 3, 1))
    return np.linalg.norm(samples[..., 0], axis=-1).mean(1)


# --------------------------------------------------------------------------- round trips


@st.composite
def rigs_and_points(draw):
    """3-8 cameras 3-8 m from the origin looking at it, evenly spread around it (azimuth
    jitter +-23 degrees, elevation -9 to 49 degrees, roll +-17 degrees; a rig of cameras all
    on one line of sight cannot triangulate), focal 500-2000 px, about half with distortion
    (|k1| < 0.2); 1-12 points within 2 m of the origin."""
    n = draw(st.integers(3, 8))
    unit = st.floats(-1.0, 1.0)
    cams = []
    for i in range(n):
        azimuth = 2 * np.pi * i / n + 0.4 * draw(unit)
        elevation = 0.35 + 0.5 * draw(unit)
        r = draw(st.floats(3000.0, 8000.0))
        center = r * np.array(
            [np.cos(azimuth) * np.cos(elevation), np.sin(azimuth) * np.cos(elevation),
             np.sin(elevation)]
        )  # fmt: skip
        dist = (0.0, 0.0, 0.0, 0.0, 0.0)
        if draw(st.booleans()):
            dist = (0.199 * draw(unit), 0.05 * draw(unit), 0.002 * draw(unit),
                    0.002 * draw(unit), 0.0)  # fmt: skip
        focal = draw(st.floats(500.0, 2000.0))
        cams.append(look_at_camera(str(i), center, focal=focal, roll=0.3 * draw(unit), dist=dist))
    m = draw(st.integers(1, 12))
    dirs = np.array([[draw(unit) for _ in range(3)] for _ in range(m)]) + 1e-3
    radii = np.array([draw(st.floats(0.0, 2000.0)) for _ in range(m)])
    points = dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * radii[:, None]
    return CameraRig(tuple(cams)), points


@pytest.mark.slow
@settings(max_examples=100, deadline=None)
@given(rigs_and_points())
def test_round_trip_dlt(case):
    rig, X = case
    kp = keypoints_of(rig, X[None])
    xy = normalised_of(rig, kp)[0]  # (J, V, 2)
    got = triangulate_dlt(rt_matrices(rig), xy, np.ones(xy.shape[:-1]))
    np.testing.assert_allclose(got, X, rtol=0, atol=1e-6)


@pytest.mark.slow
@settings(max_examples=100, deadline=None)
@given(rigs_and_points())
def test_round_trip_people(case):
    rig, X = case
    tri = triangulate_people(rig, keypoints_of(rig, X[None]))
    np.testing.assert_allclose(tri.points[0], X, rtol=0, atol=1e-6)
    assert tri.used.all() and (tri.num_views == len(rig)).all()
    assert np.nanmax(tri.reprojection_error) < 1e-6


def test_dlt_pixels_with_K_and_weights():
    """K [R | t] with undistorted pixels gives the same point; zero weight = view unused;
    fewer than two weighted views = NaN; batch axes broadcast."""
    cams = [
        look_at_camera(str(i), c, focal=900.0)
        for i, c in enumerate(np.array([[4000, 0, 1500], [0, 5000, 1000], [-3500, -3500, 2000]]))
    ]
    rig = CameraRig(tuple(cams))
    X = np.array([[100.0, -300.0, 900.0], [-500.0, 200.0, 1500.0]])
    uv = np.moveaxis(rig.project(X), 0, 1)  # (2, V, 2) pixels (no distortion)
    np.testing.assert_allclose(
        triangulate_dlt(rig.projection_matrices, uv, np.ones(3)), X, atol=1e-6
    )
    garbage = uv.copy()
    garbage[:, 1] += 300.0
    w = np.array([1.0, 0.0, 0.5])
    np.testing.assert_allclose(triangulate_dlt(rig.projection_matrices, garbage, w), X, atol=1e-6)
    out = triangulate_dlt(rig.projection_matrices, uv, np.array([[1.0, 0, 0], [0, 2.0, 1.0]]))
    assert np.isnan(out[0]).all() and np.allclose(out[1], X[1], atol=1e-6)
    nan_view = uv.copy()
    nan_view[0, 2] = np.nan  # NaN coordinates count as unseen even with a weight
    out = triangulate_dlt(rig.projection_matrices, nan_view, np.array([1.0, 0.0, 1.0]))
    assert np.isnan(out[0]).all() and np.allclose(out[1], X[1], atol=1e-6)
    batch = np.broadcast_to(uv, (4, 2, 3, 2))
    assert triangulate_dlt(rig.projection_matrices, batch, np.ones(3)).shape == (4, 2, 3)
    with pytest.raises(ValueError, match=r"points: expected \(\.\.\., 3, 2\)"):
        triangulate_dlt(rig.projection_matrices, uv[:, :2], np.ones(2))
    with pytest.raises(ValueError, match="weights"):
        triangulate_dlt(rig.projection_matrices, uv, np.ones(4))


# --------------------------------------------------------------------------- noise


def test_shelf_noise_matches_first_order_bound(shelf):
    """2 px noise on 1000 points seen by all five Shelf cameras.

    The bound is derived per point from the geometry: the expected error of the
    maximum-likelihood estimate to first order, 5.44 mm on average for these points. Over
    six seeds ours came to 0.98-1.00 times that, the plain (unit-weight) DLT 4-5% above
    ours: the rows rescaled to pixels are what makes the linear solution near-optimal.
    """
    rng = np.random.default_rng(0)
    X = shelf_points(shelf, 1000, rng)
    kp = keypoints_of(shelf, X[None])
    kp[..., :2] += rng.normal(0, 2.0, kp[..., :2].shape)
    tri = triangulate_people(shelf, kp, outlier_threshold_px=np.inf)
    err = np.linalg.norm(tri.points[0] - X, axis=-1).mean()
    bound = first_order_mean_error(shelf, X, 2.0, rng).mean()
    assert 5.2 < bound < 5.7  # the geometry is what the docstring says
    assert 0.95 * bound < err < 1.03 * bound
    xy = normalised_of(shelf, kp)[0]
    plain = triangulate_dlt(rt_matrices(shelf), xy, np.ones(xy.shape[:-1]))
    assert np.linalg.norm(plain - X, axis=-1).mean() > 1.02 * err
    # Reprojection errors are of the noise: E|2D noise| = 2 sqrt(pi / 2) = 2.5 px, less the
    # 3 degrees of freedom (of 10) that the fit absorbs.
    assert 1.9 < np.nanmean(tri.reprojection_error) < 2.3


def test_low_confidence_noisy_view_barely_hurts(shelf):
    """One view with 20 px noise: at confidence 0.15 it costs < 3% over leaving it out;
    at full confidence it would cost > 50%."""
    rng = np.random.default_rng(8)
    X = shelf_points(shelf, 400, rng)
    kp = keypoints_of(shelf, X[None])
    kp[..., :2] += rng.normal(0, 2.0, kp[..., :2].shape)
    kp[0, 3, :, :2] += rng.normal(0, 20.0, (len(X), 2))

    def mean_error(keypoints):
        tri = triangulate_people(shelf, keypoints, outlier_threshold_px=np.inf)
        return np.linalg.norm(tri.points[0] - X, axis=-1).mean()

    without = kp.copy()
    without[0, 3, :, 2] = 0.0
    low = kp.copy()
    low[0, 3, :, 2] = 0.15
    e_without, e_low, e_full = mean_error(without), mean_error(low), mean_error(kp)
    assert e_low < 1.03 * e_without
    assert e_full > 1.5 * e_without


# --------------------------------------------------------------------------- outliers


def test_outlier_view_dropped_noise_free(shelf):
    """An 80 px outlier in one of five views: the view is dropped, the point is exact and
    the dropped view's reprojection error is the 80 px."""
    rng = np.random.default_rng(9)
    X = shelf_points(shelf, 50, rng)
    kp = keypoints_of(shelf, X[None])
    bad_view = rng.integers(0, 5, len(X))
    angle = rng.uniform(0, 2 * np.pi, len(X))
    joints = np.arange(len(X))
    kp[0, bad_view, joints, :2] += 80.0 * np.column_stack([np.cos(angle), np.sin(angle)])
    tri = triangulate_people(shelf, kp)
    np.testing.assert_allclose(tri.points[0], X, atol=1e-6)
    expected_used = np.ones((len(X), 5), bool)
    expected_used[joints, bad_view] = False
    np.testing.assert_array_equal(tri.used[0], expected_used)
    assert (tri.num_views == 4).all()
    np.testing.assert_allclose(tri.reprojection_error[0, joints, bad_view], 80.0, atol=1e-6)


def test_outlier_view_dropped_with_noise(shelf):
    """2 px noise plus one 80 px outlier per joint among five views."""
    rng = np.random.default_rng(10)
    X = shelf_points(shelf, 300, rng)
    kp = keypoints_of(shelf, X[None])
    kp[..., :2] += rng.normal(0, 2.0, kp[..., :2].shape)
    bad_view = rng.integers(0, 5, len(X))
    angle = rng.uniform(0, 2 * np.pi, len(X))
    joints = np.arange(len(X))
    kp[0, bad_view, joints, :2] += 80.0 * np.column_stack([np.cos(angle), np.sin(angle)])
    tri = triangulate_people(shelf, kp)
    dropped = ~tri.used[0, joints, bad_view]
    assert dropped.mean() > 0.98
    assert (tri.num_views[0][dropped] == 4).all()
    err = np.linalg.norm(tri.points[0] - X, axis=-1)
    assert np.median(err[dropped]) < 8.0 and np.percentile(err[dropped], 95) < 15.0
    reported = tri.reprojection_error[0, joints, bad_view][dropped]
    assert np.all(np.abs(reported - 80.0) < 12.0)  # 80 px shift, plus noise and fit error


def test_two_views_with_an_outlier_keep_both(shelf):
    """With min_views views left nothing can be dropped (which of two views is wrong is
    undecidable): both stay used and the reprojection error shows the disagreement."""
    rng = np.random.default_rng(11)
    X = shelf_points(shelf, 40, rng)
    kp = keypoints_of(shelf, X[None])
    kp[0, 2:, :, 2] = 0.0  # only views 0 and 1
    # Cameras 0 and 1 are side by side: a vertical shift is across the epipolar lines
    # (a shift along them would be absorbed by the depth, invisible in any error).
    kp[0, 1, :, 1] += 80.0
    tri = triangulate_people(shelf, kp)
    assert np.isfinite(tri.points).all()
    assert tri.used[0, :, :2].all() and not tri.used[0, :, 2:].any()
    assert (tri.num_views == 2).all()
    assert np.isnan(tri.reprojection_error[0, :, 2:]).all()
    worst = np.nanmax(tri.reprojection_error[0], axis=-1)
    assert np.median(worst) > 25.0  # most joints are flagged by their error
    # The reported errors are the real ones: |project(point) - observed|.
    for v in (0, 1):
        direct = np.linalg.norm(shelf[v].project(tri.points[0]) - kp[0, v, :, :2], axis=-1)
        np.testing.assert_allclose(tri.reprojection_error[0, :, v], direct, rtol=1e-9)
    # Same with three views and min_views=3.
    kp3 = keypoints_of(shelf, X[None])
    kp3[0, 3:, :, 2] = 0.0
    kp3[0, 1, :, 1] += 80.0
    tri3 = triangulate_people(shelf, kp3, min_views=3)
    assert tri3.used[0, :, :3].all() and (tri3.num_views == 3).all()
    # ... whereas with min_views=2 the outlier goes.
    tri2 = triangulate_people(shelf, kp3)
    assert (~tri2.used[0, :, 1]).mean() > 0.9


def test_missing_and_degenerate_inputs_give_nan_not_errors(shelf):
    rng = np.random.default_rng(12)
    X = shelf_points(shelf, 6, rng).reshape(2, 3, 3)  # 2 people x 3 joints
    kp = keypoints_of(shelf, X)
    kp[0, 1:, 0, 2] = 0.0  # person 0 joint 0: one view (the others below min_confidence)
    kp[0, :, 1, :2] = np.nan  # person 0 joint 1: unseen
    kp[1, 2:, 2, :] = np.nan  # person 1 joint 2: two views
    kp[1, 0, 1, 2] = np.nan  # NaN confidence: missing
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tri = triangulate_people(shelf, kp)
        empty = triangulate_people(shelf, np.zeros((0, 5, 24, 3)))
        all_nan = triangulate_people(shelf, np.full((3, 5, 24, 3), np.nan))
        one_cam = triangulate_people(shelf.subset([2]), kp[:, 2:3])
    assert isinstance(tri, Triangulation) and tri.num_people == 2
    assert np.isnan(tri.points[0, :2]).all() and not tri.used[0, :2].any()
    assert (tri.num_views[0, :2] == 0).all() and np.isnan(tri.reprojection_error[0, :2]).all()
    np.testing.assert_allclose(tri.points[1], X[1], atol=1e-6)
    np.testing.assert_allclose(tri.points[0, 2], X[0, 2], atol=1e-6)
    assert tri.num_views.tolist() == [[0, 0, 5], [5, 4, 2]]
    assert np.isnan(tri.reprojection_error[1, 1, 0]) and not tri.used[1, 1, 0]

    assert empty.points.shape == (0, 24, 3) and empty.reprojection_error.shape == (0, 24, 5)
    assert empty.used.shape == (0, 24, 5) and empty.num_views.shape == (0, 24)
    assert np.isnan(all_nan.points).all() and not all_nan.used.any()
    assert np.isnan(all_nan.reprojection_error).all() and (all_nan.num_views == 0).all()
    assert np.isnan(one_cam.points).all() and (one_cam.num_views == 0).all()


def test_bad_arguments(shelf):
    with pytest.raises(ValueError, match=r"keypoints: expected \(num_people, 5 views"):
        triangulate_people(shelf, np.zeros((1, 4, 24, 3)))
    with pytest.raises(ValueError, match="min_views"):
        triangulate_people(shelf, np.zeros((1, 5, 24, 3)), min_views=1)


def test_distorted_rig_reprojection_uses_distortion():
    """On a rig with strong distortion the reported errors equal |Camera.project - observed|,
    and an outlier is still found."""
    cams = [
        look_at_camera(str(i), c, focal=700.0, dist=(-0.18, 0.03, 0.001, -0.001, 0.0))
        for i, c in enumerate(
            np.array([[4000, 0, 1500], [0, 5000, 1000], [-3500, -3500, 2000], [2500, -4000, 800]])
        )
    ]
    rig = CameraRig(tuple(cams))
    rng = np.random.default_rng(13)
    X = rng.uniform(-1200, 1200, (1, 30, 3))
    kp = keypoints_of(rig, X)
    kp[0, 2, 5, :2] += 60.0
    tri = triangulate_people(rig, kp)
    np.testing.assert_allclose(tri.points, X, atol=1e-6)
    assert not tri.used[0, 5, 2] and tri.used.sum() == 4 * 30 - 1
    for v, cam in enumerate(rig):
        direct = np.linalg.norm(cam.project(tri.points[0]) - kp[0, v, :, :2], axis=-1)
        np.testing.assert_allclose(tri.reprojection_error[0, :, v], direct, atol=1e-6)


def test_people_are_independent_of_batching(shelf):
    """Solving people together (as the benchmark's batched mode does) or one at a time
    gives the same result, outlier rounds included."""
    rng = np.random.default_rng(14)
    X = shelf_points(shelf, 120, rng).reshape(5, 24, 3)
    kp = keypoints_of(shelf, X, conf=0.8)
    kp[..., :2] += rng.normal(0, 2.0, kp[..., :2].shape)
    bad = rng.uniform(size=kp.shape[:-1]) < 0.1
    kp[..., :2] += bad[..., None] * rng.uniform(-150, 150, kp[..., :2].shape)
    kp[rng.uniform(size=kp.shape[:-1]) < 0.1] = np.nan
    together = triangulate_people(shelf, kp)
    for p in range(len(X)):
        alone = triangulate_people(shelf, kp[p : p + 1])
        np.testing.assert_allclose(alone.points[0], together.points[p], atol=1e-9)
        np.testing.assert_array_equal(alone.used[0], together.used[p])
        np.testing.assert_allclose(
            alone.reprojection_error[0], together.reprojection_error[p], atol=1e-9
        )
    assert (~together.used & np.isfinite(together.reprojection_error)).any()  # some dropped
