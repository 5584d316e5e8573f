"""Synthetic calibration footage: a ChArUco board drawn by OpenCV, warped into known cameras.

Board: 7x5 squares of 60 mm, markers 45 mm, DICT_4X4_50. Cameras: pinhole, no distortion,
looking at a volume about 1.6 m away (world mm, OpenCV world-to-camera ``x = R X + t``).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.calibrate.board import Board
from pipeline.data.cameras import Camera, CameraRig

BOARD = Board("charuco", 7, 5, 60.0, 45.0, "DICT_4X4_50")
SPEC = "charuco:7x5:0.06:0.045:DICT_4X4_50"
PX_PER_MM = 1.5
MARGIN_MM = 20.0
SUPER = 3


def look_at(name: str, centre, target, *, size=(640, 480), f=600.0, roll_deg=0.0) -> Camera:
    """A camera at ``centre`` looking at ``target`` (world mm), world z up."""
    z = np.asarray(target, float) - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world
    R = Rotation.from_rotvec([0, 0, np.radians(roll_deg)]).as_matrix() @ R
    w, h = size
    K = np.array([[f, 0, w / 2 + 3.0], [0, f, h / 2 - 2.0], [0, 0, 1]])
    return Camera(name, w, h, K, np.zeros(5), R, -R @ np.asarray(centre, float))


def default_rig() -> CameraRig:
    """Three cameras around the volume; the third rolled 90 deg with a portrait image."""
    target = np.array([0.0, 0.0, 1000.0])
    return CameraRig(
        (
            look_at("left", [-1200.0, -1100.0, 1300.0], target),
            look_at("front", [0.0, -1600.0, 1200.0], target),
            look_at("right", [1200.0, -1100.0, 1100.0], target, size=(480, 640), roll_deg=90),
        )
    )


def board_image(*, inverted: bool = False) -> np.ndarray:
    """The board as an image with a white margin, PX_PER_MM pixels per mm."""
    w = int(round((BOARD.columns * BOARD.square_mm + 2 * MARGIN_MM) * PX_PER_MM))
    h = int(round((BOARD.rows * BOARD.square_mm + 2 * MARGIN_MM) * PX_PER_MM))
    image = BOARD.opencv_board().generateImage((w, h), marginSize=int(MARGIN_MM * PX_PER_MM))
    return 255 - image if inverted else image


def checkerboard_image(board: Board) -> np.ndarray:
    """A checkerboard of ``board``'s squares (the first black) with a white margin, in the
    same frame as :func:`board_image` (board mm (0, 0) at the squares' outer corner)."""
    step = board.square_mm * PX_PER_MM
    margin = MARGIN_MM * PX_PER_MM
    w = int(round(board.columns * step + 2 * margin))
    h = int(round(board.rows * step + 2 * margin))
    y, x = np.mgrid[0:h, 0:w] + 0.5  # pixel centres
    i, j = np.floor((x - margin) / step), np.floor((y - margin) / step)
    inside = (i >= 0) & (i < board.columns) & (j >= 0) & (j < board.rows)
    return np.where(inside & ((i + j) % 2 == 0), 0, 255).astype(np.uint8)


def board_poses(num: int, seed: int = 0) -> list[np.ndarray]:
    """(4, 4) ``T_world_board`` poses: the board near (0, 0, 1000) facing -y (the cameras),
    tilted up to ~35 deg."""
    rng = np.random.default_rng(seed)
    base = Rotation.from_euler("x", -90, degrees=True)  # board y down -> world -z; normal -> +y
    out = []
    for _ in range(num):
        tilt = Rotation.from_rotvec(rng.uniform(-0.8, 0.8, 3))
        T = np.eye(4)
        T[:3, :3] = (tilt * base).as_matrix()
        centre = np.array([rng.uniform(-250, 250), rng.uniform(-200, 200), rng.uniform(850, 1150)])
        T[:3, 3] = centre - T[:3, :3] @ [BOARD.columns * 30.0, BOARD.rows * 30.0, 0]
        out.append(T)
    return out


def moving_board(t: float) -> np.ndarray:
    """(4, 4) ``T_world_board`` of a board carried smoothly through the volume, at time
    ``t`` in frames (30-60 mm and about 1 deg per frame)."""
    base = Rotation.from_euler("x", -90, degrees=True)
    tilt = Rotation.from_rotvec([0.25 * np.sin(0.11 * t), 0.25 * np.sin(0.07 * t + 1.0),
                                 0.2 * np.cos(0.05 * t)])  # fmt: skip
    T = np.eye(4)
    T[:3, :3] = (tilt * base).as_matrix()
    centre = np.array([250 * np.sin(0.2 * t), 150 * np.sin(0.15 * t + 0.5),
                       1000 + 150 * np.cos(0.17 * t)])  # fmt: skip
    T[:3, 3] = centre - T[:3, :3] @ [BOARD.columns * 30.0, BOARD.rows * 30.0, 0]
    return T


def render(cam: Camera, T_world_board: np.ndarray, board_img: np.ndarray, rng) -> np.ndarray:
    """The grey image camera ``cam`` takes of the board (blur and noise added)."""
    T_cam_board = np.eye(4)
    T_cam_board[:3, :3], T_cam_board[:3, 3] = cam.R, cam.t
    T_cam_board = T_cam_board @ T_world_board
    pix_to_mm = np.array(
        [
            [1 / PX_PER_MM, 0, 0.5 / PX_PER_MM - MARGIN_MM],
            [0, 1 / PX_PER_MM, 0.5 / PX_PER_MM - MARGIN_MM],
            [0, 0, 1],
        ]
    )
    # drawn at SUPER times the resolution, then averaged down (no aliasing)
    up = np.diag([SUPER, SUPER, 1.0]) @ np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1]])
    H = up @ cam.K @ T_cam_board[:3, [0, 1, 3]] @ pix_to_mm
    H = np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1]]) @ H
    size = (cam.width * SUPER, cam.height * SUPER)
    background = np.full(size[::-1], 110, np.uint8)
    facing = T_cam_board[:3, 2] @ T_cam_board[:3, 3] > 0  # the normal points away from us
    if facing and (T_cam_board[2, 3] > 0):
        warped = cv2.warpPerspective(board_img, H, size, flags=cv2.INTER_LINEAR)
        mask = cv2.warpPerspective(np.ones_like(board_img), H, size, flags=cv2.INTER_NEAREST)
        background = np.where(mask > 0, warped, background)
    small = cv2.resize(background, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
    image = cv2.GaussianBlur(small, (3, 3), 0.6).astype(float)
    image += rng.normal(0, 2.0, image.shape)
    return np.clip(image, 0, 255).astype(np.uint8)


def write_session(
    root: Path, rig: CameraRig, poses: list[np.ndarray] | dict[str, list[np.ndarray]], *,
    inverted: bool = False, blank: dict[str, set[int]] | None = None, seed: int = 0,
    image: np.ndarray | None = None,
) -> list[Path]:  # fmt: skip
    """One folder of PNG frames per camera under ``root``; ``poses``: the board per frame,
    or per camera name its board per frame; ``blank[name]``: frames that camera does not
    see the board in; ``image``: the board drawn (default: :data:`BOARD`, see
    :func:`board_image`)."""
    rng = np.random.default_rng(seed)
    board = board_image(inverted=inverted) if image is None else image
    folders = []
    for cam in rig:
        folder = root / cam.name
        folder.mkdir(parents=True)
        for k, T in enumerate(poses[cam.name] if isinstance(poses, dict) else poses):
            hidden = k in (blank or {}).get(cam.name, set())
            image = (
                render(cam, T, board, rng)
                if not hidden
                else np.full((cam.height, cam.width), 110, np.uint8)
            )
            cv2.imwrite(str(folder / f"{k:04d}.png"), image)
        folders.append(folder)
    return folders
