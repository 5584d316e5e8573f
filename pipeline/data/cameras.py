"""Calibrated pinhole cameras with OpenCV distortion, and the rig that holds them.

Conventions (the native scene format): world in millimetres, z up; OpenCV
world-to-camera extrinsics ``x_cam = R @ X + t``; camera axes x right, y down,
z forward; distortion ``dist = (k1, k2, p1, p2, k3)`` as in OpenCV.
"""

from __future__ import annotations

import functools
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core.files import SceneFormatError, atomic_write
from pipeline.core.schema import check_numbers


@dataclass(frozen=True, eq=False)
class Camera:
    """One calibrated camera.

    Attributes:
        name: unique name within a rig (also the name of its video / image folder).
        width, height: image size in pixels.
        K: (3, 3) intrinsic matrix.
        dist: (5,) OpenCV distortion k1, k2, p1, p2, k3.
        R: (3, 3) world-to-camera rotation.
        t: (3,) world-to-camera translation, mm.
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world mm: ``-R.T @ t``."""
        return -self.R.T @ self.t

    @property
    def P(self) -> np.ndarray:
        """(3, 4) projection matrix ``K [R | t]`` of the undistorted pinhole."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    @property
    def T_world_camera(self) -> np.ndarray:
        """(4, 4) camera-to-world transform (the camera's pose in the world)."""
        T = np.eye(4)
        T[:3, :3] = self.R.T
        T[:3, 3] = self.center
        return T

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) world mm -> (..., 3) camera mm."""
        return np.asarray(points, float) @ self.R.T + self.t

    def project(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) world mm -> (..., 2) distorted pixels; points behind the camera are NaN."""
        return distort_and_project(self.world_to_camera(points), self.K, self.dist)

    def pixels_to_rays(self, pixels: np.ndarray) -> np.ndarray:
        """(..., 2) distorted pixels -> (..., 3) unit ray directions in world coordinates."""
        normalised = self.undistort_to_normalised(pixels)
        d_cam = np.concatenate([normalised, np.ones(normalised.shape[:-1] + (1,))], axis=-1)
        d = d_cam @ self.R  # R.T @ d for row vectors
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def undistort_to_normalised(self, pixels: np.ndarray) -> np.ndarray:
        """(..., 2) distorted pixels -> (..., 2) undistorted normalised image coordinates."""
        pixels = np.asarray(pixels, float)
        flat = pixels.reshape(-1, 1, 2)
        if flat.shape[0] == 0:
            return pixels.copy()
        finite = np.isfinite(flat).all(axis=-1)[:, 0]
        out = np.full(flat.shape, np.nan)
        if finite.any():
            # Through inv(K) first: cv2.undistortPoints ignores K's skew, project() does not.
            homo = np.concatenate([flat[finite, 0], np.ones((int(finite.sum()), 1))], 1)
            distorted = (homo @ np.linalg.inv(self.K).T)[:, None, :2]
            import cv2  # OpenCV's ~0.05 s import: here, not in every process

            criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
            out[finite] = cv2.undistortPoints(distorted, np.eye(3), self.dist, criteria=criteria)
        return out.reshape(pixels.shape)

    def undistort_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """(..., 2) distorted pixels -> (..., 2) pixels of the ideal pinhole ``K``."""
        n = self.undistort_to_normalised(pixels)
        return n @ self.K[:2, :2].T + self.K[:2, 2]

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "width": int(self.width),
            "height": int(self.height),
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
        }


@functools.lru_cache(maxsize=64)
def _fold_radius2(k1: float, k2: float, k3: float) -> float:
    r2 = np.linspace(0.0, 100.0, 20001)
    slope = 1 + r2 * (3 * k1 + r2 * (5 * k2 + r2 * 7 * k3))
    bad = np.flatnonzero(slope <= 0)
    return float(r2[bad[0]]) if bad.size else np.inf


def max_valid_radius2(dist: np.ndarray) -> float:
    """Squared normalised radius beyond which the radial distortion folds back.

    ``r_d = r (1 + k1 r^2 + k2 r^4 + k3 r^6)`` stops increasing where its derivative
    ``1 + 3 k1 r^2 + 5 k2 r^4 + 7 k3 r^6`` first reaches 0; points beyond would land
    back inside the image. Returns inf when it never folds (within r <= 10).
    """
    k1, k2, _, _, k3 = (float(x) for x in dist)
    return _fold_radius2(k1, k2, k3)


def distort_and_project(points_cam: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """OpenCV's projection model, vectorised.

    Args:
        points_cam: (..., 3) points in camera coordinates.
        K: (3, 3) intrinsics; dist: (5,) k1, k2, p1, p2, k3.
    Returns:
        (..., 2) pixels; NaN where the point is not in front of the camera or lies past
        the radius where the distortion folds back.
    """
    p = np.asarray(points_cam, float)
    z = p[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(z > 1e-9, p[..., 0] / z, np.nan)
        y = np.where(z > 1e-9, p[..., 1] / z, np.nan)
    k1, k2, p1, p2, k3 = dist
    r2 = x * x + y * y
    # Past the distortion's fold a point would land back inside the image: not visible.
    r2 = np.where(r2 <= max_valid_radius2(dist), r2, np.nan)
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    u = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
    v = K[1, 1] * yd + K[1, 2]
    return np.stack([u, v], axis=-1)


@dataclass(frozen=True, eq=False)
class CameraRig:
    """The cameras of one scene, in a fixed order (a view index is a position here)."""

    cameras: tuple[Camera, ...]

    def __post_init__(self) -> None:
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise ValueError(f"camera names must be unique, got {names}")

    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self):
        return iter(self.cameras)

    def __getitem__(self, i: int) -> Camera:
        return self.cameras[i]

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def index_of(self, name: str) -> int:
        for i, c in enumerate(self.cameras):
            if c.name == name:
                return i
        raise KeyError(f"no camera named {name!r}; cameras are {self.names}")

    @property
    def projection_matrices(self) -> np.ndarray:
        """(num_views, 3, 4) undistorted projection matrices."""
        return np.stack([c.P for c in self.cameras])

    @property
    def centers(self) -> np.ndarray:
        """(num_views, 3) camera centres, world mm."""
        return np.stack([c.center for c in self.cameras])

    def project(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) world mm -> (num_views, ..., 2) distorted pixels."""
        return np.stack([c.project(points) for c in self.cameras])

    def subset(self, indices: list[int]) -> CameraRig:
        return CameraRig(tuple(self.cameras[i] for i in indices))


# --------------------------------------------------------------------------- validation / io


def make_camera(
    *,
    name: str,
    width: int,
    height: int,
    K,
    dist,
    R,
    t,
    source: str | os.PathLike = "<memory>",
    field: str = "cameras",
) -> Camera:
    """Build a :class:`Camera`, checking every field; errors name ``source`` and the field."""

    def arr(value, key: str, shape: tuple[int, ...], also=()) -> np.ndarray:
        check_numbers(value, source, f"{field}.{key}")
        try:
            a = np.asarray(value, dtype=float)
        except (TypeError, ValueError) as exc:
            raise SceneFormatError(source, f"{field}.{key}", f"not numeric ({exc})") from exc
        if a.shape != shape and a.shape not in also:
            raise SceneFormatError(
                source, f"{field}.{key}", f"expected shape {shape}, got {a.shape}"
            )
        if not np.isfinite(a).all():
            raise SceneFormatError(source, f"{field}.{key}", "contains NaN or infinity")
        return a

    if not isinstance(name, str) or not name:
        raise SceneFormatError(
            source, f"{field}.name", f"expected a non-empty string, got {name!r}"
        )
    for key, v in (("width", width), ("height", height)):
        if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v <= 0:
            if not (isinstance(v, float) and v.is_integer() and v > 0):
                raise SceneFormatError(
                    source, f"{field}.{key}", f"expected a positive integer, got {v!r}"
                )
    K = arr(K, "K", (3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        raise SceneFormatError(
            source, f"{field}.K", "expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0"
        )
    check_numbers(dist, source, f"{field}.dist")
    try:
        d = np.asarray(dist, dtype=float).ravel()
    except (TypeError, ValueError) as exc:
        raise SceneFormatError(source, f"{field}.dist", f"not numeric ({exc})") from exc
    if d.size == 4:
        d = np.append(d, 0.0)
    if d.size != 5:
        raise SceneFormatError(
            source, f"{field}.dist", f"expected 5 values (k1 k2 p1 p2 k3), got {d.size}"
        )
    d = arr(d, "dist", (5,))
    R = arr(R, "R", (3, 3))
    ortho_err = np.abs(R @ R.T - np.eye(3)).max()
    if ortho_err > 1e-4 or np.linalg.det(R) < 0:
        raise SceneFormatError(
            source,
            f"{field}.R",
            f"expected a rotation matrix (R R^T = I, det +1); |R R^T - I| = {ortho_err:.2g}, "
            f"det = {np.linalg.det(R):.4f}",
        )
    t = arr(t, "t", (3,), also=((3, 1), (1, 3))).ravel()
    return Camera(name=name, width=int(width), height=int(height), K=K, dist=d, R=R, t=t)


def load_cameras(path: str | os.PathLike) -> CameraRig:
    """Read a native ``cameras.json`` (a list of camera objects, see sample_data/README.md)."""
    path = Path(path)
    if not path.is_file():
        raise SceneFormatError(path, None, "file not found")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise SceneFormatError(path, None, f"not valid JSON ({exc})") from exc
    if isinstance(data, dict) and "cameras" in data:
        data = data["cameras"]
    if not isinstance(data, list) or not data:
        raise SceneFormatError(path, "cameras", "expected a non-empty list of cameras")
    cams = []
    for i, c in enumerate(data):
        if not isinstance(c, dict):
            raise SceneFormatError(path, f"cameras[{i}]", "expected an object")
        missing = [k for k in ("name", "width", "height", "K", "R", "t") if k not in c]
        if missing:
            raise SceneFormatError(path, f"cameras[{i}]", f"missing keys {missing}")
        cams.append(
            make_camera(
                name=c["name"],
                width=c["width"],
                height=c["height"],
                K=c["K"],
                dist=c.get("dist", [0, 0, 0, 0, 0]),
                R=c["R"],
                t=c["t"],
                source=path,
                field=f"cameras[{i}]",
            )
        )
    names = [c.name for c in cams]
    if len(set(names)) != len(names):
        raise SceneFormatError(path, "cameras[].name", f"names must be unique, got {names}")
    return CameraRig(tuple(cams))


def save_cameras(rig: CameraRig, path: str | os.PathLike) -> None:
    """Write a native ``cameras.json`` atomically."""
    text = json.dumps([c.to_dict() for c in rig.cameras], indent=1)
    with atomic_write(path, "w") as fh:
        fh.write(text + "\n")
