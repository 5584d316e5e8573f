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
4. A bundle adjustment over every camera pose (the first fixed: it is the frame) and every
   board pose, intrinsics fixed, robust loss (``soft_l1``, 1 px), sparse Jacobian.

Transforms are 4x4 ``T_to_from``; millimetres; camera axes as OpenCV (x right, y down,
z forward).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
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
        T_root_board: frame -> (4, 4) board pose in the root camera's frame.
        residuals: per view (same order as the views given), (N, 2) reprojection error, px.
    """

    T_camera_root: dict[int, np.ndarray]
    T_root_board: dict[int, np.ndarray]
    residuals: list[np.ndarray]


def _pack(T: np.ndarray) -> np.ndarray:
    return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])


def _unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, 6) -> (M, 3, 3) rotations, (M, 3) translations."""
    return Rotation.from_rotvec(x[:, :3]).as_matrix(), x[:, 3:]


def bundle_adjust(  # long: the problem's set-up, solve and unpacking read as one
    views: list[View],
    object_points: np.ndarray,
    intrinsics: dict[int, tuple[np.ndarray, np.ndarray]],
    T_camera_root: dict[int, np.ndarray],
    T_cam_board: list[np.ndarray],
    *,
    f_scale_px: float = 1.0,
) -> Adjusted:
    """Refine camera and board poses together (see the module docstring, step 4).

    Args:
        views: the views of cameras in ``T_camera_root`` (others are ignored).
        object_points: (num_corners, 3) board corners, mm.
        intrinsics: camera -> (K (3, 3), dist (5,)), held fixed.
        T_camera_root: camera -> initial (4, 4) pose; the first key is held fixed.
        T_cam_board: per view, its (4, 4) board pose (seeds each frame's board).
    """
    cams = list(T_camera_root)
    free = cams[1:]
    used = [k for k, v in enumerate(views) if v.camera in T_camera_root]
    frames = sorted({views[k].frame for k in used})
    # seed each board from the view with the most corners
    seed: dict[int, int] = {}
    for k in used:
        f = views[k].frame
        if f not in seed or len(views[k].ids) > len(views[seed[f]].ids):
            seed[f] = k
    boards0 = [np.linalg.inv(T_camera_root[views[seed[f]].camera]) @ T_cam_board[seed[f]]
               for f in frames]  # fmt: skip
    x0 = np.concatenate([np.ravel([_pack(T_camera_root[c]) for c in free]),
                         np.ravel([_pack(T) for T in boards0])])  # fmt: skip
    cam_slot = {c: i for i, c in enumerate(free)}
    frame_slot = {f: i for i, f in enumerate(frames)}
    # one row per observed corner
    obs_cam = np.concatenate([np.full(len(views[k].ids), views[k].camera) for k in used])
    obs_frame = np.concatenate(
        [np.full(len(views[k].ids), frame_slot[views[k].frame]) for k in used]
    )
    obs_pt = object_points[np.concatenate([views[k].ids for k in used])]
    obs_px = np.concatenate([views[k].pixels for k in used])
    n_cam = 6 * len(free)

    def project(x: np.ndarray) -> np.ndarray:
        Rc, tc = (
            _unpack(x[:n_cam].reshape(-1, 6)) if free else (np.zeros((0, 3, 3)), np.zeros((0, 3)))
        )
        Rb, tb = _unpack(x[n_cam:].reshape(-1, 6))
        X = np.einsum("nij,nj->ni", Rb[obs_frame], obs_pt) + tb[obs_frame]  # root frame
        out = np.empty((len(X), 2))
        for c in cams:
            m = obs_cam == c
            Xc = X[m] if c == cams[0] else X[m] @ Rc[cam_slot[c]].T + tc[cam_slot[c]]
            out[m] = distort_and_project(Xc, *intrinsics[c])
        return out

    def residual(x: np.ndarray) -> np.ndarray:
        r = project(x) - obs_px
        return np.nan_to_num(r, nan=1e3).ravel()

    rows = len(obs_px)
    sparsity = lil_matrix((2 * rows, len(x0)), dtype=np.uint8)
    for i in range(rows):
        b = n_cam + 6 * obs_frame[i]
        sparsity[2 * i : 2 * i + 2, b : b + 6] = 1
        if obs_cam[i] in cam_slot:
            a = 6 * cam_slot[obs_cam[i]]
            sparsity[2 * i : 2 * i + 2, a : a + 6] = 1
    sol = least_squares(residual, x0, jac_sparsity=sparsity, loss="soft_l1",
                        f_scale=f_scale_px, x_scale="jac", method="trf")  # fmt: skip
    r = (project(sol.x) - obs_px).reshape(-1, 2)
    cam_poses = {cams[0]: np.eye(4)}
    if free:
        Rc, tc = _unpack(sol.x[:n_cam].reshape(-1, 6))
        cam_poses |= {c: transform(Rc[i], tc[i]) for c, i in cam_slot.items()}
    Rb, tb = _unpack(sol.x[n_cam:].reshape(-1, 6))
    boards = {f: transform(Rb[i], tb[i]) for f, i in frame_slot.items()}
    residuals: list[np.ndarray] = [np.zeros((0, 2))] * len(views)
    start = 0
    for k in used:
        n = len(views[k].ids)
        residuals[k] = r[start : start + n]
        start += n
    return Adjusted(T_camera_root=cam_poses, T_root_board=boards, residuals=residuals)
