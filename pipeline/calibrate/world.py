"""The world frame of a calibration.

By default the world is the first calibrated camera's frame (OpenCV axes: x right, y down,
z forward). With a floor frame, the board as seen in that frame is laid on the floor: the
origin at the board's corner (its point (0, 0, 0)), x along the board's columns, z up =
the board's normal on the side of the cameras, y completing a right-handed frame. Units mm.
"""

from __future__ import annotations

import numpy as np

from pipeline.core.files import SceneFormatError


def floor_transform(
    T_root_board: np.ndarray, camera_centres_root: np.ndarray, *, source: str = "--floor-frame"
) -> np.ndarray:
    """(4, 4) ``T_world_root`` putting the board on the floor (see the module docstring).

    Args:
        T_root_board: (4, 4) the board's pose in the root frame, mm.
        camera_centres_root: (num_cameras, 3) camera centres in the root frame, mm.
    """
    R_b, origin = T_root_board[:3, :3], T_root_board[:3, 3]
    x, normal = R_b[:, 0], R_b[:, 2]
    side = np.median((camera_centres_root - origin) @ normal)
    if abs(side) < 1e-9:
        raise SceneFormatError(source, None, "the cameras lie in the board's plane")
    z = normal if side > 0 else -normal
    y = np.cross(z, x)
    R_root_world = np.stack([x, y, z], axis=1)  # world axes in root coordinates
    T_root_world = np.eye(4)
    T_root_world[:3, :3], T_root_world[:3, 3] = R_root_world, origin
    return np.linalg.inv(T_root_world)
