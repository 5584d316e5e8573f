"""Camera poses from board views: board poses per view, camera pairs, a spanning tree and
a bundle adjustment.

1. Each view of the board gives the board's pose in that camera (``cv2.solvePnP``, the
   planar IPPE solution, refined).
2. Two cameras seeing the board in the same frame give their relative pose
   ``T_b_a = T_b_board @ inv(T_a_board)``; over all shared frames, the robust mean (the
   rotation nearest the others in the median, averaged with its neighbours within 2 deg;
   the translations' component-wise median).
3. A spanning tree of the pairs, most shared frames first, places every camera in the
   first camera's frame; each frame's board is placed from the camera that sees the most
   of its corners.
4. A bundle adjustment over every camera pose (the first fixed: it is the frame), every
   board pose and every camera's time offset, intrinsics fixed, robust loss (``soft_l1``,
   1 px), sparse Jacobian. The board is moved by hand, so it moves between frames: each
   camera sees it at its own time (:class:`BoardPath`, :func:`bundle_adjust`). On the
   shared four-webcam session one camera's frames are 0.84 frame early against the sync
   table; modelled, its residual goes from 2.0 to 0.6 px RMS.

Transforms are 4x4 ``T_to_from``; millimetres; camera axes as OpenCV (x right, y down,
z forward).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.spatial.transform import Rotation

from pipeline.data.cameras import distort_and_project


@dataclass(frozen=True)
class View:
    """The board seen by one camera in one frame.

    Attributes:
        camera: the camera's index; frame: the (synchronised) frame index.
        ids: (N,) corner ids; pixels: (N, 2) their pixels.
    """

    camera: int
    frame: int
    ids: np.ndarray
    pixels: np.ndarray


def transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, np.ravel(t)
    return T


def board_pose(
    object_points: np.ndarray, pixels: np.ndarray, K: np.ndarray, dist: np.ndarray
) -> np.ndarray:
    """(4, 4) ``T_camera_board`` from (N, 3) board points (mm) seen at (N, 2) pixels."""
    obj = object_points.astype(np.float64)
    img = pixels.astype(np.float64).reshape(-1, 1, 2)
    ok, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok or not len(rvecs):
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist)
        rvecs, tvecs = [rvec], [tvec]
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvecs[0].copy(), tvecs[0].copy())
    return transform(cv2.Rodrigues(rvec)[0], tvec)


def robust_mean_pose(poses: list[np.ndarray]) -> np.ndarray:
    """(4, 4) robust mean of (4, 4) transforms (see the module docstring, step 2)."""
    Rs = np.stack([p[:3, :3] for p in poses])
    ts = np.stack([p[:3, 3] for p in poses])
    # angle between every two rotations
    cos = (np.einsum("aij,bij->ab", Rs, Rs) - 1) / 2
    angles = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    centre = int(np.argmin(np.median(angles, axis=1)))
    near = angles[centre] <= 2.0
    R = Rotation.from_matrix(Rs[near]).mean().as_matrix()
    return transform(R, np.median(ts[near], axis=0))


def spanning_tree(num_cameras: int, shared: dict[tuple[int, int], int], root: int) -> dict:
    """Parent of each camera reachable from ``root`` (root -> None) in the maximum spanning
    tree of the pair graph (edge weight: shared frames; Prim's order from ``root``)."""
    parent: dict[int, int | None] = {root: None}
    while True:
        best = None
        for (a, b), n in shared.items():
            for u, v in ((a, b), (b, a)):
                if u in parent and v not in parent and (best is None or n > best[0]):
                    best = (n, u, v)
        if best is None:
            return parent
        parent[best[2]] = best[1]


def initial_poses(
    views: list[View], T_cam_board: list[np.ndarray], cameras: list[int]
) -> tuple[dict[int, np.ndarray], dict[tuple[int, int], int]]:
    """``T_camera_root`` of every camera connected to ``cameras[0]`` (root: identity), and
    the shared-frame count of every pair."""
    by_frame: dict[int, dict[int, int]] = {}
    for k, v in enumerate(views):
        by_frame.setdefault(v.frame, {})[v.camera] = k
    pairs: dict[tuple[int, int], list[np.ndarray]] = {}
    for seen in by_frame.values():
        for a in seen:
            for b in seen:
                if a < b:
                    T = T_cam_board[seen[b]] @ np.linalg.inv(T_cam_board[seen[a]])
                    pairs.setdefault((a, b), []).append(T)
    shared = {ab: len(ts) for ab, ts in pairs.items()}
    parent = spanning_tree(len(cameras), shared, cameras[0])
    poses = {cameras[0]: np.eye(4)}
    for cam in parent:  # parents come before their children
        p = parent[cam]
        if p is None:
            continue
        T_cam_p = (robust_mean_pose(pairs[(p, cam)]) if p < cam
                   else np.linalg.inv(robust_mean_pose(pairs[(cam, p)])))  # fmt: skip
        poses[cam] = T_cam_p @ poses[p]
    return poses, shared


@dataclass(frozen=True)
class Adjusted:
    """The bundle adjustment's result.

    Attributes:
        T_camera_root: camera index -> (4, 4) pose (the root camera: identity).
        T_root_board: frame -> (4, 4) board pose in the root camera's frame at the frame's
            time (see :func:`bundle_adjust`).
        residuals: per view (same order as the views given), (N, 2) reprojection error, px.
        time_offsets: camera index -> its time offset (the times' unit; root: 0).
        frame_period: the median time between two frames (the times' unit).
    """

    T_camera_root: dict[int, np.ndarray]
    T_root_board: dict[int, np.ndarray]
    residuals: list[np.ndarray]
    time_offsets: dict[int, float]
    frame_period: float


def _pack(T: np.ndarray) -> np.ndarray:
    return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])


def _unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, 6) -> (M, 3, 3) rotations, (M, 3) translations."""
    return Rotation.from_rotvec(x[:, :3]).as_matrix(), x[:, 3:]


class BoardPath:
    """The board's motion: a pose per frame (a knot, at the frame's time), linear in time
    between the knots of consecutive frames (translation linear, rotation along the
    geodesic), extended along the same line up to :attr:`REACH` frames past either end of
    a run of consecutive frames; held at the nearest knot beyond."""

    REACH = 2.0

    def __init__(self, frames: list[int], knot_times: np.ndarray) -> None:
        self.frames = np.asarray(frames)
        self.times = np.asarray(knot_times, float)

    def bracket(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per time in (V,) ``t``: knots a, b and the weight of b (pose = a + w (b - a))."""
        n = len(self.times)
        k = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, max(n - 2, 0))
        a, b = k, np.minimum(k + 1, n - 1)
        with np.errstate(divide="ignore", invalid="ignore"):
            w = np.nan_to_num((t - self.times[a]) / (self.times[b] - self.times[a]))
        out = (w < 0) | (w > 1) | ((self.frames[b] - self.frames[a]) != 1)
        # a gap or past an end: the nearer knot, extended along its run of frames
        e = np.where(np.abs(t - self.times[a]) <= np.abs(t - self.times[b]), a, b)
        before = t < self.times[e]
        lo = np.where(before, e, np.maximum(e - 1, 0))
        hi = np.where(before, np.minimum(e + 1, n - 1), e)
        run = (hi != lo) & ((self.frames[hi] - self.frames[lo]) == 1)
        with np.errstate(divide="ignore", invalid="ignore"):
            w_ext = np.nan_to_num((t - self.times[lo]) / (self.times[hi] - self.times[lo]))
        w_ext = np.clip(w_ext, -self.REACH, 1 + self.REACH)
        a = np.where(out, np.where(run, lo, e), a)
        b = np.where(out, np.where(run, hi, e), b)
        w = np.where(out, np.where(run, w_ext, 0.0), np.where(a == b, 0.0, w))
        return a, b, w

    def span(self, t_lo: np.ndarray, t_hi: np.ndarray) -> list[range]:
        """Per view, the knots its pose can depend on for times in [t_lo, t_hi]."""
        n = len(self.times)
        lo = np.clip(np.searchsorted(self.times, t_lo, side="right") - 2, 0, n - 1)
        hi = np.clip(np.searchsorted(self.times, t_hi, side="right") + 1, 0, n - 1)
        return [range(a, b + 1) for a, b in zip(lo, hi, strict=True)]

    @staticmethod
    def poses(knots: np.ndarray, a, b, w) -> tuple[np.ndarray, np.ndarray]:
        """(K, 6) knot poses (rotation vector, translation) -> per bracket (V, 3, 3), (V, 3)."""
        R = rotvec_to_matrix(knots[:, :3])
        Ra, Rb = R[a], R[b]
        step = matrix_to_rotvec(np.einsum("vji,vjk->vik", Ra, Rb))  # Ra^T Rb
        Rw = Ra @ rotvec_to_matrix(w[:, None] * step)
        return Rw, knots[a, 3:] + w[:, None] * (knots[b, 3:] - knots[a, 3:])


def rotvec_to_matrix(v: np.ndarray) -> np.ndarray:
    """(N, 3) rotation vectors -> (N, 3, 3) matrices (Rodrigues)."""
    theta = np.linalg.norm(v, axis=1)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    k = v / safe[:, None]
    K = np.zeros((len(v), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K -= K.transpose(0, 2, 1)
    s = np.where(small, 0.0, np.sin(theta))[:, None, None]
    c = np.where(small, 0.0, 1 - np.cos(theta))[:, None, None]
    out = np.eye(3) + s * K + c * (K @ K)
    if small.any():  # first order: I + [v]x
        V = np.zeros((small.sum(), 3, 3))
        vs = v[small]
        V[:, 0, 1], V[:, 0, 2], V[:, 1, 2] = -vs[:, 2], vs[:, 1], -vs[:, 0]
        out[small] = np.eye(3) + V - V.transpose(0, 2, 1)
    return out


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations -> (N, 3) rotation vectors (angles below about 3 rad exact; the
    steps between neighbouring frames are far smaller)."""
    cos = np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    theta = np.arccos(cos)
    axis = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], 1)
    sin = np.sin(theta)
    scale = np.where(sin > 1e-6, theta / (2 * np.where(sin > 1e-6, sin, 1.0)), 0.5)
    out = axis * scale[:, None]
    wide = theta > 3.0  # near pi the axis from the antisymmetric part is ill-conditioned
    if wide.any():
        out[wide] = Rotation.from_matrix(R[wide]).as_rotvec()
    return out


def frame_times(times: np.ndarray | None, frames: list[int]) -> tuple[np.ndarray, float]:
    """Each frame's time (the median of its cameras' times) and the frame period (the
    median step between consecutive frames); the frame index and 1 without times."""
    if times is None:
        return np.asarray(frames, float), 1.0
    per_frame = np.nanmedian(np.where(np.isfinite(times), times, np.nan), axis=1)
    steps = np.diff(per_frame)
    steps = steps[np.isfinite(steps) & (steps > 0)]
    period = float(np.median(steps)) if len(steps) else 1.0
    knot = per_frame[frames]
    if not (np.all(np.isfinite(knot)) and np.all(np.diff(knot) > 0)):
        return np.asarray(frames, float) * period, period  # times out of order: by index
    return knot, period


def bundle_adjust(  # long: the problem's set-up, solve and unpacking read as one
    views: list[View],
    object_points: np.ndarray,
    intrinsics: dict[int, tuple[np.ndarray, np.ndarray]],
    T_camera_root: dict[int, np.ndarray],
    T_cam_board: list[np.ndarray],
    *,
    times: np.ndarray | None = None,
    max_offset_frames: float | None = 2.0,
    f_scale_px: float = 1.0,
) -> Adjusted:
    """Refine camera poses, board poses and the cameras' time offsets together (see the
    module docstring, step 4).

    The board moves: its pose is a :class:`BoardPath` through one knot per frame, and a
    camera sees it at the time its frame was taken, ``times[frame, camera] + offset``,
    with one offset per camera (the root's held at 0). A camera whose frames are late or
    early against the sync (webcams stamping frames when they arrive, a frame matched to
    the wrong one) then sees the board where it was, not where the others saw it.

    Args:
        views: the views of cameras in ``T_camera_root`` (others are ignored).
        object_points: (num_corners, 3) board corners, mm.
        intrinsics: camera -> (K (3, 3), dist (5,)), held fixed.
        T_camera_root: camera -> initial (4, 4) pose; the first key is held fixed.
        T_cam_board: per view, its (4, 4) board pose (seeds each frame's board).
        times: (num_frames, num_cameras) when each camera took each frame (any unit,
            e.g. a sync table's seconds; NaN: unknown); None: the frame index.
        max_offset_frames: bound of the time offsets, in frame periods; None holds them
            at 0 (the cameras as synchronised as ``times`` says).
    """
    cams = list(T_camera_root)
    free = cams[1:]
    used = [k for k, v in enumerate(views) if v.camera in T_camera_root]
    frames = sorted({views[k].frame for k in used})
    knot_t, period = frame_times(times, frames)
    path = BoardPath(frames, knot_t)
    # seed each board from the view with the most corners
    seed: dict[int, int] = {}
    for k in used:
        f = views[k].frame
        if f not in seed or len(views[k].ids) > len(views[seed[f]].ids):
            seed[f] = k
    boards0 = [np.linalg.inv(T_camera_root[views[seed[f]].camera]) @ T_cam_board[seed[f]]
               for f in frames]  # fmt: skip
    fit_offsets = max_offset_frames is not None and max_offset_frames > 0 and bool(free)
    bound = (max_offset_frames or 0.0) * period
    cam_slot = {c: i for i, c in enumerate(free)}
    frame_slot = {f: i for i, f in enumerate(frames)}
    n_cam, n_off = 6 * len(free), (len(free) if fit_offsets else 0)
    x0 = np.concatenate([np.ravel([_pack(T_camera_root[c]) for c in free]), np.zeros(n_off),
                         np.ravel([_pack(T) for T in boards0])])  # fmt: skip
    # per view: its camera, its frame's knot, its time as stamped
    v_cam = np.array([views[k].camera for k in used])
    v_time = np.array(
        [
            knot_t[frame_slot[views[k].frame]]
            if times is None or not np.isfinite(times[views[k].frame, views[k].camera])
            else times[views[k].frame, views[k].camera]
            for k in used
        ]
    )
    v_off = np.array([cam_slot.get(c, -1) for c in v_cam])
    # one row per observed corner
    obs_view = np.concatenate([np.full(len(views[k].ids), i) for i, k in enumerate(used)])
    obs_cam = v_cam[obs_view]
    obs_pt = object_points[np.concatenate([views[k].ids for k in used])]
    obs_px = np.concatenate([views[k].pixels for k in used])

    cam_rows = [(c, np.flatnonzero(obs_cam == c)) for c in cams]

    def offsets(x: np.ndarray) -> np.ndarray:
        if not fit_offsets:
            return np.zeros(len(used))
        off = bound * np.tanh(x[n_cam : n_cam + n_off])  # smooth within +-bound
        return np.where(v_off >= 0, off[np.maximum(v_off, 0)], 0.0)

    def project(x: np.ndarray) -> np.ndarray:
        pose = x[:n_cam].reshape(-1, 6)
        Rc, tc = rotvec_to_matrix(pose[:, :3]), pose[:, 3:]
        knots = x[n_cam + n_off :].reshape(-1, 6)
        Rb, tb = BoardPath.poses(knots, *path.bracket(v_time + offsets(x)))
        X = np.einsum("nij,nj->ni", Rb[obs_view], obs_pt) + tb[obs_view]  # root frame
        out = np.empty((len(X), 2))
        for c, m in cam_rows:
            Xc = X[m] if c == cams[0] else X[m] @ Rc[cam_slot[c]].T + tc[cam_slot[c]]
            out[m] = distort_and_project(Xc, *intrinsics[c])
        return out

    def residual(x: np.ndarray) -> np.ndarray:
        r = project(x) - obs_px
        return np.nan_to_num(r, nan=1e3).ravel()

    reach = bound if fit_offsets else 0.0
    spans = path.span(v_time - reach, v_time + reach)
    # the Jacobian's pattern: each corner's two rows against its view's knots, camera pose
    # and time offset
    view_cols = []
    for v in range(len(used)):
        cols = [n_cam + n_off + 6 * k + j for k in spans[v] for j in range(6)]
        if v_off[v] >= 0:
            cols += [6 * v_off[v] + j for j in range(6)]
            if fit_offsets:
                cols.append(n_cam + v_off[v])
        view_cols.append(np.asarray(cols))
    row_idx = [np.repeat(np.arange(2 * i, 2 * i + 2), len(view_cols[v]))
               for i, v in enumerate(obs_view)]  # fmt: skip
    col_idx = [np.tile(view_cols[v], 2) for v in obs_view]
    sparsity = coo_matrix(
        (np.ones(sum(map(len, row_idx)), np.uint8),
         (np.concatenate(row_idx), np.concatenate(col_idx))),
        shape=(2 * len(obs_px), len(x0)),
    ).tocsr()  # fmt: skip
    sol = least_squares(residual, x0, jac_sparsity=sparsity, loss="soft_l1", f_scale=f_scale_px,
                        x_scale="jac", method="trf")  # fmt: skip
    r = (project(sol.x) - obs_px).reshape(-1, 2)
    cam_poses = {cams[0]: np.eye(4)}
    if free:
        Rc, tc = _unpack(sol.x[:n_cam].reshape(-1, 6))
        cam_poses |= {c: transform(Rc[i], tc[i]) for c, i in cam_slot.items()}
    Rb, tb = _unpack(sol.x[n_cam + n_off :].reshape(-1, 6))
    boards = {f: transform(Rb[i], tb[i]) for f, i in frame_slot.items()}
    residuals: list[np.ndarray] = [np.zeros((0, 2))] * len(views)
    start = 0
    for k in used:
        n = len(views[k].ids)
        residuals[k] = r[start : start + n]
        start += n
    offs = {c: 0.0 for c in cams}
    if fit_offsets:
        offs |= {c: float(bound * np.tanh(sol.x[n_cam + i])) for c, i in cam_slot.items()}
    return Adjusted(T_camera_root=cam_poses, T_root_board=boards, residuals=residuals,
                    time_offsets=offs, frame_period=period)  # fmt: skip
