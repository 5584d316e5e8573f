"""Calibration errors, found and fixed from the people themselves.

Per camera, its 2D against the joints the *other* cameras triangulate
(:mod:`pipeline.diagnose.reference`): the residual as a vector field over the image
(a rotated camera shifts the whole field one way; a moved one shifts near people more
than far ones; wrong intrinsics grow it toward the edges) and as a time series (a
camera knocked during the capture shows a step). The camera that disagrees most is
named first and left out of the others' references before the next is judged (one bad
camera inflates everybody's residual a little, its own a lot).

A suspect camera's pose (and optionally its focal length) is refined by a bundle
adjustment (``scipy.optimize.least_squares``, sparse Jacobian): that camera's 6 pose
parameters and every reference joint's 3D position, against the 2D of all cameras, the
other cameras held fixed (they fix the gauge: the world frame stays theirs). The
correction it makes is the calibration error reported.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.spatial.transform import Rotation

from pipeline.data.cameras import Camera, CameraRig
from pipeline.data.scene import Scene
from pipeline.diagnose.reference import MIN_CONFIDENCE, triangulate_without
from pipeline.results.store import PipelineResults

GRID = (8, 6)  # cells of the residual field over the image (columns, rows)
SUSPECT_RATIO = 2.0  # systematic residual this many times the other cameras' median
MIN_SUSPECT_PX = 3.0  # ... and at least this much more, px
MAX_BA_POINTS = 8000  # joints in the bundle adjustment (a subsample of a long clip)
HUBER_PX = 5.0  # robust loss scale of the bundle adjustment


@dataclass(frozen=True, eq=False)
class CameraResidual:
    """One camera's 2D against the other cameras' joints. Arrays over its R observations."""

    camera: str
    frame: np.ndarray  # (R,) frame of each observation
    pixel: np.ndarray  # (R, 2) where it was seen (its own 2D)
    vector: np.ndarray  # (R, 2) reprojected reference minus own 2D, px

    @property
    def magnitude(self) -> np.ndarray:
        return np.linalg.norm(self.vector, axis=-1)

    @property
    def median_px(self) -> float:
        return float(np.median(self.magnitude)) if len(self.frame) else float("nan")

    def systematic_px(self, width: int, height: int, *, min_count: int = 20) -> float:
        """Median over image cells (with >= ``min_count`` observations) of the length of
        the cell's mean residual vector: the part of the residual that does not average
        out. Detector noise does (a few px at most on real data, where 2D and calibration
        never agree to the pixel); a rotated or moved camera's shift does not."""
        f = self.field(width, height)
        keep = f["count"] >= min_count
        if not keep.any():
            return float("nan")
        return float(np.median(np.linalg.norm(f["mean"][keep], axis=-1)))

    def field(self, width: int, height: int, grid: tuple[int, int] = GRID) -> dict:
        """Mean residual vector per image cell: ``{"centers": (C, 2), "mean": (C, 2),
        "count": (C,)}`` over the cells with observations."""
        gx = np.clip((self.pixel[:, 0] / width * grid[0]).astype(int), 0, grid[0] - 1)
        gy = np.clip((self.pixel[:, 1] / height * grid[1]).astype(int), 0, grid[1] - 1)
        cell = gy * grid[0] + gx
        n = np.bincount(cell, minlength=grid[0] * grid[1])
        sx = np.bincount(cell, self.vector[:, 0], minlength=n.size)
        sy = np.bincount(cell, self.vector[:, 1], minlength=n.size)
        have = np.flatnonzero(n > 0)
        cx = (have % grid[0] + 0.5) * width / grid[0]
        cy = (have // grid[0] + 0.5) * height / grid[1]
        mean = np.stack([sx[have], sy[have]], -1) / n[have, None]
        return {"centers": np.stack([cx, cy], -1), "mean": mean, "count": n[have]}

    def series(self, num_frames: int) -> np.ndarray:
        """(F,) median residual per frame, px; NaN where the camera saw nobody."""
        out = np.full(num_frames, np.nan)
        mag = self.magnitude
        order = np.argsort(self.frame, kind="stable")
        f, m = self.frame[order], mag[order]
        starts = np.flatnonzero(np.r_[True, f[1:] != f[:-1]])
        for a, b in zip(starts, np.r_[starts[1:], len(f)], strict=True):
            out[f[a]] = np.median(m[a:b])
        return out


def camera_residual(
    scene: Scene, results: PipelineResults, view: int, exclude: frozenset[int] = frozenset()
) -> CameraResidual:
    """Camera ``view``'s own 2D (of the detections the run gave each person) against the
    person's joints triangulated without it (and without ``exclude``)."""
    cam = scene.rig[view]
    X = triangulate_without(scene, results, frozenset({view}) | exclude)  # (Q, J, 3)
    rows = results.person_members[:, view]
    q = np.flatnonzero(rows >= 0)
    kp = results.det_joints2d[rows[q]]  # (n, J, 3)
    proj = cam.project(X[q])  # (n, J, 2)
    ok = np.isfinite(proj).all(-1) & np.isfinite(kp[..., :2]).all(-1)
    ok &= np.nan_to_num(kp[..., 2]) >= MIN_CONFIDENCE
    qq, jj = np.nonzero(ok)
    return CameraResidual(
        camera=cam.name,
        frame=results.person_frame[q[qq]],
        pixel=kp[qq, jj, :2],
        vector=proj[qq, jj] - kp[qq, jj, :2],
    )


@dataclass(frozen=True, eq=False)
class StepChange:
    """A jump in a camera's residual over time: it moved at ``frame``."""

    frame: int
    before_px: float
    after_px: float


def find_step(series: np.ndarray, *, min_side: int = 20, min_jump_px: float = 3.0):
    """The most significant single step in a per-frame residual series, or None.

    The split that maximises the difference of the medians either side, kept when it
    exceeds ``min_jump_px``, half the smaller side's median (people walking nearer and
    farther change a camera's residual by tens of percent) and 4 robust standard errors.
    """
    f = np.flatnonzero(np.isfinite(series))
    if len(f) < 2 * min_side:
        return None
    x = series[f]
    best, best_i = 0.0, -1
    for i in range(min_side, len(x) - min_side + 1):
        d = abs(np.median(x[i:]) - np.median(x[:i]))
        if d > best:
            best, best_i = d, i
    if best_i < 0:
        return None
    a, b = x[:best_i], x[best_i:]
    mad = lambda v: 1.4826 * np.median(np.abs(v - np.median(v)))  # noqa: E731
    se = np.sqrt(mad(a) ** 2 / len(a) + mad(b) ** 2 / len(b)) * 1.25  # median's efficiency
    if best < max(min_jump_px, 0.5 * min(np.median(a), np.median(b)), 4 * se):
        return None
    return StepChange(int(f[best_i]), float(np.median(a)), float(np.median(b)))


@dataclass(frozen=True, eq=False)
class CalibrationFinding:
    """One camera's verdict; the errors are those the bundle adjustment corrected."""

    camera: str
    residual_px: float  # median, against the other cameras' joints
    systematic_px: float  # the residual that does not average out (CameraResidual)
    others_systematic_px: float  # the same of the cameras not suspected
    suspect: bool
    step: StepChange | None = None
    rotation_error_deg: float = 0.0
    translation_error_mm: float = 0.0
    focal_error_px: float = 0.0
    residual_after_px: float = float("nan")
    refined: Camera | None = None
    # Set by pipeline.diagnose.in_sync when the camera's 2D was re-timed before judging:
    retimed_by_frames: float = 0.0  # the sync offset applied to it
    systematic_as_recorded_px: float = float("nan")  # its systematic residual without it
    out_of_sync: bool = False  # a suspect as recorded, not once re-timed

    def to_dict(self) -> dict:
        out = {
            "suspect": bool(self.suspect),
            "residual_px": round(self.residual_px, 2),
            "systematic_px": round(self.systematic_px, 2),
            "others_systematic_px": round(self.others_systematic_px, 2),
            "rotation_error_deg": round(self.rotation_error_deg, 3),
            "translation_error_mm": round(self.translation_error_mm, 1),
            "focal_error_px": round(self.focal_error_px, 1),
            "residual_after_px": round(self.residual_after_px, 2),
            "moved_at_frame": None if self.step is None else self.step.frame,
            "out_of_sync": bool(self.out_of_sync),
        }
        if self.retimed_by_frames:
            out["retimed_by_frames"] = round(self.retimed_by_frames, 3)
            out["systematic_as_recorded_px"] = round(self.systematic_as_recorded_px, 2)
        if self.step is not None:
            out["residual_before_after_step_px"] = [
                round(self.step.before_px, 2), round(self.step.after_px, 2)
            ]  # fmt: skip
        return out


def check_calibration(
    scene: Scene,
    results: PipelineResults,
    *,
    refine: bool = True,
    refine_focal: bool = False,
) -> dict[str, CalibrationFinding]:
    """Every camera judged; suspects (worst first, each left out of the next judgements)
    refined by :func:`refine_camera` when ``refine``."""
    V = len(scene.rig)
    bad: list[int] = []
    while True:
        residuals = [camera_residual(scene, results, v, frozenset(bad) - {v}) for v in range(V)]
        systematic = np.array(
            [r.systematic_px(c.width, c.height) for r, c in zip(residuals, scene.rig, strict=True)]
        )
        rest = [v for v in range(V) if v not in bad]
        if len(rest) <= 3:  # a camera needs 2 others to be judged, and a majority to agree
            break
        worst = max(rest, key=lambda v: np.nan_to_num(systematic[v], nan=-1))
        others = np.nanmedian([systematic[v] for v in rest if v != worst])
        if not systematic[worst] > max(SUSPECT_RATIO * others, others + MIN_SUSPECT_PX):
            break
        bad.append(worst)
    findings = {}
    for v, cam in enumerate(scene.rig):
        excl = frozenset(bad) - {v}
        res = residuals[v]
        good = [u for u in range(V) if u != v and u not in bad]
        step = find_step(res.series(results.num_frames))
        finding = CalibrationFinding(
            camera=cam.name,
            residual_px=res.median_px,
            systematic_px=float(systematic[v]),
            others_systematic_px=float(np.nanmedian(systematic[good])),
            suspect=v in bad,
            step=step,
        )
        if refine and v in bad:
            finding = _with_refinement(scene, results, v, excl, finding, refine_focal)
        findings[cam.name] = finding
    return findings


def _with_refinement(scene, results, view, exclude, finding, refine_focal):
    cam = scene.rig[view]
    new = refine_camera(scene, results, view, exclude=exclude, refine_focal=refine_focal)
    dR = Rotation.from_matrix(new.R @ cam.R.T).magnitude()
    after = camera_residual(
        dataclasses.replace(scene, rig=replace_camera(scene.rig, view, new)), results, view, exclude
    )
    return dataclasses.replace(
        finding,
        rotation_error_deg=float(np.degrees(dR)),
        translation_error_mm=float(np.linalg.norm(new.center - cam.center)),
        focal_error_px=float(new.K[0, 0] - cam.K[0, 0]),
        residual_after_px=after.median_px,
        refined=new,
    )


def replace_camera(rig: CameraRig, view: int, camera: Camera) -> CameraRig:
    cams = list(rig)
    cams[view] = camera
    return CameraRig(tuple(cams))


# --------------------------------------------------------------------------- bundle adjustment


@dataclass(frozen=True, eq=False)
class _Observations:
    """The bundle adjustment's data: P points seen O times."""

    point: np.ndarray  # (O,) index of the 3D point
    view: np.ndarray  # (O,) camera
    normalised: np.ndarray  # (O, 2) undistorted normalised 2D
    scale: np.ndarray  # (O,) focal length (px per normalised unit) of the camera
    weight: np.ndarray  # (O,) confidence
    start: np.ndarray  # (P, 3) initial 3D points, mm


def _observations(scene, results, view, exclude, *, seed=0) -> _Observations:
    """Joints seen by ``view`` and >= 2 other (non-excluded) cameras: their initial 3D
    (triangulated without ``view``) and every used observation of them."""
    X = triangulate_without(scene, results, frozenset({view}) | exclude)
    members = results.person_members
    own = members[:, view] >= 0
    kp_own = np.full(X.shape[:2], 0.0)
    kp_own[own] = np.nan_to_num(results.det_joints2d[members[own, view], :, 2])
    good = np.isfinite(X).all(-1) & (kp_own >= MIN_CONFIDENCE)  # (Q, J)
    qs, js = np.nonzero(good)
    if len(qs) > MAX_BA_POINTS:
        pick = np.sort(np.random.default_rng(seed).choice(len(qs), MAX_BA_POINTS, replace=False))
        qs, js = qs[pick], js[pick]
    cams = [v for v in range(len(scene.rig)) if v not in exclude]
    point, vis, norm, scale, weight = [], [], [], [], []
    for v in cams:
        rows = members[qs, v]
        have = rows >= 0
        kp = results.det_joints2d[rows[have], js[have]]  # (n, 3)
        use = np.nan_to_num(kp[:, 2]) >= MIN_CONFIDENCE
        if v != view:
            use &= results.person_used[qs[have], js[have], v]
        idx = np.flatnonzero(have)[use]
        cam = scene.rig[v]
        point.append(idx)
        vis.append(np.full(len(idx), v))
        norm.append(cam.undistort_to_normalised(kp[use, :2]))
        scale.append(np.full(len(idx), 0.5 * (cam.K[0, 0] + cam.K[1, 1])))
        weight.append(kp[use, 2])
    return _Observations(
        point=np.concatenate(point), view=np.concatenate(vis),
        normalised=np.concatenate(norm), scale=np.concatenate(scale),
        weight=np.concatenate(weight), start=X[qs, js],
    )  # fmt: skip


@dataclass(frozen=True, eq=False)
class _CameraAdjustment:
    """The bundle adjustment's parameters ``x = [w (3), t (3), (focal scale), X (P, 3)]``:
    the camera's rotation is ``exp([w]) R0`` (w starts at 0), the other cameras fixed.
    Residuals are px (normalised coordinates times the focal length), each observation
    weighted by the square root of its confidence."""

    obs: _Observations
    R0: np.ndarray  # (3, 3) the camera's recorded rotation
    Rs: np.ndarray  # (O, 3, 3) the observing camera's rotation (fixed ones)
    ts: np.ndarray  # (O, 3)
    mine: np.ndarray  # (O,) bool: seen by the refined camera
    n_cam: int  # 6, or 7 with the focal scale
    sw: np.ndarray  # (O, 1)

    @property
    def own(self) -> np.ndarray:
        return np.flatnonzero(self.mine)

    def camera_frame(self, x: np.ndarray):
        R, t = self.Rs.copy(), self.ts.copy()
        R[self.mine] = Rotation.from_rotvec(x[:3]).as_matrix() @ self.R0
        t[self.mine] = x[3:6]
        X = x[self.n_cam :].reshape(-1, 3)[self.obs.point]
        return R, X, np.einsum("oij,oj->oi", R, X) + t

    def residuals(self, x: np.ndarray) -> np.ndarray:
        _, _, Xc = self.camera_frame(x)
        uv = Xc[:, :2] / Xc[:, 2:3]
        if self.n_cam == 7:
            uv[self.mine] *= x[6]  # the focal's relative change scales the normalised plane
        return ((uv - self.obs.normalised) * self.sw).ravel()

    def jacobian(self, x: np.ndarray):
        R, X, Xc = self.camera_frame(x)
        own, n_cam, O = self.own, self.n_cam, len(Xc)
        z = Xc[:, 2]
        dpi = np.zeros((O, 2, 3))  # d(x/z, y/z) / d Xc
        dpi[:, 0, 0] = dpi[:, 1, 1] = 1 / z
        dpi[:, 0, 2] = -Xc[:, 0] / z**2
        dpi[:, 1, 2] = -Xc[:, 1] / z**2
        focal = np.where(self.mine, x[6], 1.0)[:, None, None] if n_cam == 7 else 1.0
        d_xc = dpi * self.sw[:, :, None] * focal  # (O, 2, 3)
        RX = np.einsum("oij,oj->oi", R[own], X[own])
        skew = np.zeros((len(own), 3, 3))  # d(exp([w]) R0 X)/dw ~ -[R X]x near the solution
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = RX[:, 2], -RX[:, 1], RX[:, 0]
        skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = -RX[:, 2], RX[:, 1], -RX[:, 0]
        blocks = [d_xc[own] @ skew, d_xc[own]]  # rotation, translation
        if n_cam == 7:
            blocks.append((Xc[own, :2] / Xc[own, 2:3] * self.sw[own])[:, :, None])
        r2 = 2 * np.arange(O)[:, None] + np.arange(2)  # (O, 2) residual rows
        rows = np.concatenate([np.repeat(r2.ravel(), 3), np.repeat(r2[own].ravel(), n_cam)])
        pcols = n_cam + 3 * self.obs.point[:, None, None] + np.arange(3)  # (O, 1, 3)
        cols = np.concatenate([
            np.broadcast_to(pcols, (O, 2, 3)).ravel(),
            np.broadcast_to(np.arange(n_cam), (len(own), 2, n_cam)).ravel(),
        ])  # fmt: skip
        vals = np.concatenate([(d_xc @ R).ravel(), np.concatenate(blocks, axis=2).ravel()])
        return coo_matrix((vals, (rows, cols)), shape=(2 * O, len(x))).tocsr()


def refine_camera(
    scene: Scene,
    results: PipelineResults,
    view: int,
    *,
    exclude: frozenset[int] = frozenset(),
    refine_focal: bool = False,
) -> Camera:
    """Camera ``view`` with its pose (and focal length) refined by bundle adjustment."""
    obs = _observations(scene, results, view, exclude)
    cam = scene.rig[view]
    if len(obs.start) < 10:
        raise ValueError(f"camera {cam.name}: too few joints seen with other cameras to refine")
    ba = _CameraAdjustment(
        obs=obs, R0=cam.R, Rs=np.stack([c.R for c in scene.rig])[obs.view],
        ts=np.stack([c.t for c in scene.rig])[obs.view], mine=obs.view == view,
        n_cam=7 if refine_focal else 6, sw=(np.sqrt(obs.weight) * obs.scale)[:, None],
    )  # fmt: skip
    cam0 = np.concatenate([np.zeros(3), cam.t, [1.0] if refine_focal else []])
    points0 = obs.start.ravel()
    # 1. Resection: the camera alone against the other cameras' joints (dense, 6-7
    # parameters). A pose off by a degree puts all its residuals far out in the robust
    # loss's tail, where the joint problem creeps; this brings them into its core.
    rows = (2 * ba.own[:, None] + np.arange(2)).ravel()
    resect = least_squares(
        lambda c: ba.residuals(np.concatenate([c, points0]))[rows],
        cam0,
        jac=lambda c: ba.jacobian(np.concatenate([c, points0]))[rows][:, : ba.n_cam].toarray(),
        loss="soft_l1", f_scale=4 * HUBER_PX, x_scale="jac", max_nfev=50,
    )  # fmt: skip
    # 2. The bundle adjustment: that camera and every joint, all observations.
    fit = least_squares(
        ba.residuals, np.concatenate([resect.x, points0]), jac=ba.jacobian, loss="huber",
        f_scale=HUBER_PX, x_scale="jac", method="trf", tr_solver="lsmr", max_nfev=50,
    )  # fmt: skip
    K = cam.K.copy()
    if refine_focal:
        K[:2, :2] *= fit.x[6]
    R = Rotation.from_rotvec(fit.x[:3]).as_matrix() @ cam.R
    return dataclasses.replace(cam, R=R, t=fit.x[3:6].copy(), K=K)
