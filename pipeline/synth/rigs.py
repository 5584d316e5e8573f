"""Synthetic camera rigs: a Panoptic-like dome of HD cameras.

World millimetres, z up, floor at z = 0; cameras as in :mod:`pipeline.data.cameras`
(``x_cam = R @ X + t``, x right, y down, z forward).

The CMU Panoptic studio has 31 HD cameras (1920 x 1080, focal length about 1400-1650
px) spread over a geodesic dome, at many heights, all aimed at the middle of the
capture floor. :func:`dome_rig` builds the same kind of rig: cameras on rings of a
hemisphere centred on the floor's centre, the rings at different heights, the cameras
of neighbouring rings staggered in azimuth, every camera looking at a point one metre
above the floor's centre. People are meant to stand inside ``capture_radius_mm`` of
the centre (:func:`dome_capture_radius`), where every part of the floor is seen whole
by many cameras; outside it they come close to the cameras and leave most images.
"""

from __future__ import annotations

import re

import numpy as np

from pipeline.data.cameras import Camera, CameraRig

__all__ = ["DOME_RADIUS_MM", "dome_capture_radius", "dome_rig", "look_at", "parse_dome_spec"]

DOME_RADIUS_MM = 4000.0
"""Default dome radius: larger than Panoptic's (about 2.75 m) so that 20 people fit
inside the capture circle with the synthesiser's 650 mm spacing."""
HD_SIZE = (1920, 1080)
HD_FOCAL_PX = 1400.0  # Panoptic's HD cameras: fx ~ 1390-1650 px at 1920 x 1080
_TARGET_HEIGHT_MM = 1000.0
# ring heights as fractions of the dome radius: low, eye level, high, top (Panoptic's
# panels cover the dome from near the floor to the crown)
_RING_HEIGHTS = (0.15, 0.4, 0.65, 0.85)


def look_at(center: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R (3, 3), t (3,)) of a camera at ``center`` (mm) looking at
    ``target`` with the world's z axis up in the image (image y points down)."""
    z = np.asarray(target, float) - np.asarray(center, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    if np.linalg.norm(x) < 1e-9:  # looking straight down or up: any x will do
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ np.asarray(center, float)


def _ring_sizes(num_cameras: int, heights: tuple[float, ...]) -> list[int]:
    """Cameras per ring, proportional to each ring's circumference, each ring >= 1."""
    circ = np.sqrt(1.0 - np.asarray(heights) ** 2)
    share = num_cameras * circ / circ.sum()
    sizes = np.maximum(np.floor(share).astype(int), 1)
    while sizes.sum() < num_cameras:  # largest remainders first
        sizes[np.argmax(share - sizes)] += 1
    while sizes.sum() > num_cameras:
        sizes[np.argmax(sizes)] -= 1
    return [int(s) for s in sizes]


def dome_rig(
    num_cameras: int,
    *,
    radius_mm: float = DOME_RADIUS_MM,
    focal_px: float = HD_FOCAL_PX,
    size: tuple[int, int] = HD_SIZE,
) -> CameraRig:
    """``num_cameras`` HD cameras on a dome (hemisphere of ``radius_mm`` centred on the
    floor at the origin), on 1-4 rings at different heights, aimed at (0, 0, 1 m).

    Fewer than 4 cameras make one ring at eye level; 4-7 two rings; 8-15 three; 16 and
    more four. Cameras are named ``hd_<ring>_<index>`` (Panoptic's naming); no lens
    distortion. Deterministic.
    """
    if num_cameras < 1:
        raise ValueError(f"a dome needs at least 1 camera, got {num_cameras}")
    if not radius_mm > 2 * _TARGET_HEIGHT_MM:
        raise ValueError(f"dome radius must exceed 2000 mm, got {radius_mm}")
    n_rings = 1 if num_cameras < 4 else 2 if num_cameras < 8 else 3 if num_cameras < 16 else 4
    heights = {1: (0.4,), 2: (0.25, 0.55), 3: (0.2, 0.45, 0.7), 4: _RING_HEIGHTS}[n_rings]
    w, h = size
    K = np.array([[focal_px, 0.0, (w - 1) / 2], [0.0, focal_px, (h - 1) / 2], [0.0, 0.0, 1.0]])
    target = np.array([0.0, 0.0, _TARGET_HEIGHT_MM])
    cams = []
    sizes = _ring_sizes(num_cameras, heights)
    for ring, (frac, count) in enumerate(zip(heights, sizes, strict=True)):
        z = frac * radius_mm
        r = np.sqrt(radius_mm**2 - z**2)
        # odd rings offset by half a step: neighbouring rings do not line up
        az = 2 * np.pi * (np.arange(count) + 0.5 * (ring % 2)) / count
        for i, a in enumerate(az):
            center = np.array([r * np.cos(a), r * np.sin(a), z])
            R, t = look_at(center, target)
            cams.append(Camera(f"hd_{ring:02d}_{i:02d}", w, h, K.copy(), np.zeros(5), R, t))
    return CameraRig(tuple(cams))


def dome_capture_radius(radius_mm: float = DOME_RADIUS_MM) -> float:
    """Radius (mm) of the floor circle people stand in: 0.6 of the dome's, which keeps
    everyone 1.6 m or more from the nearest camera of a 4 m dome."""
    return 0.6 * radius_mm


_DOME = re.compile(r"^dome:(\d+)(?::(\d+(?:\.\d*)?))?$", re.IGNORECASE)


def parse_dome_spec(spec: str) -> tuple[int, float] | None:
    """``dome:N`` or ``dome:N:RADIUS_MM`` -> (N, radius mm); None for any other spec.

    Raises ValueError for a ``dome:`` spec that does not parse.
    """
    if not spec.lower().startswith("dome"):
        return None
    m = _DOME.match(spec.strip())
    if not m or int(m.group(1)) < 1:
        raise ValueError(
            f"--rig {spec!r}: expected dome:N (N >= 1 cameras) or dome:N:RADIUS_MM, "
            "e.g. dome:16 or dome:31:4500"
        )
    return int(m.group(1)), float(m.group(2)) if m.group(2) else DOME_RADIUS_MM
