#!/usr/bin/env python3
"""Write a ring rig's ``cameras.json``: N cameras on a circle, looking inwards.

For scale scenes: ``mvviz synth --rig ring.json``. Camera ``i`` stands at
angle ``2 pi i / N`` on a circle of ``--radius`` mm at ``--height`` mm and looks at a
point ``--aim-height`` mm above the floor on a circle of ``--aim-radius`` mm, at the
opposite angle turned by ``--aim-turn`` degrees. ``--aim-radius 0`` is the classic ring
(everyone looks at the centre: people inside are seen by most cameras); a wide ring
with aims spread over the floor and a longer focal length (``--focal``) sees each
person with a few cameras, many of them from far away.

World mm, z up; OpenCV extrinsics (x right, y down, z forward); no distortion.

Usage::

    python tools/make_ring_rig.py /tmp/ring16.json --cameras 16 --radius 7000
    python tools/make_ring_rig.py /tmp/wide16.json --cameras 16 --radius 12000 \\
        --aim-radius 5000 --aim-turn 30 --focal 2200
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from pipeline.data.cameras import Camera, CameraRig, make_camera, save_cameras


def look_at(
    name: str,
    center: np.ndarray,
    target: np.ndarray,
    *,
    focal: float,
    width: int = 1920,
    height: int = 1080,
) -> Camera:
    """A pinhole at ``center`` (3,) mm looking at ``target`` (3,) mm, image x level (z up)."""
    forward = target - center
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])  # world-to-camera rows: camera x, y, z in the world
    K = [[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]]
    return make_camera(
        name=name, width=width, height=height, K=K, dist=(0, 0, 0, 0, 0), R=R, t=-R @ center
    )


def ring_rig(
    num_cameras: int,
    *,
    radius_mm: float = 7000.0,
    height_mm: float = 2500.0,
    aim_radius_mm: float = 0.0,
    aim_turn_deg: float = 0.0,
    aim_height_mm: float = 1000.0,
    focal_px: float = 1100.0,
    width: int = 1920,
    height: int = 1080,
) -> CameraRig:
    """The ring of the module docstring: cameras ``ring00``, ``ring01``, ..."""
    if num_cameras < 2:
        raise ValueError(f"a ring needs at least 2 cameras, got {num_cameras}")
    cams = []
    for i in range(num_cameras):
        a = 2 * np.pi * i / num_cameras
        c = np.array([radius_mm * np.cos(a), radius_mm * np.sin(a), height_mm])
        b = a + np.pi + np.radians(aim_turn_deg)
        target = np.array([aim_radius_mm * np.cos(b), aim_radius_mm * np.sin(b), aim_height_mm])
        cams.append(look_at(f"ring{i:02d}", c, target, focal=focal_px, width=width, height=height))
    return CameraRig(tuple(cams))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("out", type=Path, help="cameras.json to write")
    p.add_argument("--cameras", type=int, default=16)
    p.add_argument("--radius", type=float, default=7000.0, help="ring radius, mm")
    p.add_argument("--height", type=float, default=2500.0, help="camera height, mm")
    p.add_argument("--aim-radius", type=float, default=0.0, help="circle the aims lie on, mm")
    p.add_argument("--aim-turn", type=float, default=0.0, help="aim angle offset, degrees")
    p.add_argument("--aim-height", type=float, default=1000.0, help="aim height, mm")
    p.add_argument("--focal", type=float, default=1100.0, help="focal length, px")
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--image-height", type=int, default=1080)
    args = p.parse_args(argv)
    rig = ring_rig(
        args.cameras,
        radius_mm=args.radius,
        height_mm=args.height,
        aim_radius_mm=args.aim_radius,
        aim_turn_deg=args.aim_turn,
        aim_height_mm=args.aim_height,
        focal_px=args.focal,
        width=args.width,
        height=args.image_height,
    )
    save_cameras(rig, args.out)
    print(f"wrote {args.out}: {len(rig)} cameras on a {args.radius / 1000:.1f} m ring")
    return 0


if __name__ == "__main__":
    sys.exit(main())
