"""Qualisys QTM calibrations (``.qca.txt``, XML) read into (and written from) a native rig.

Native convention (see :mod:`pipeline.data.cameras`): world millimetres, z up, OpenCV
world-to-camera extrinsics ``x_cam = R @ X + t``, distortion ``(k1, k2, p1, p2, k3)``.

The file, as QTM exports it and as Pose2Sim ships it with its demos::

    <calibration ...>
      <cameras>
        <camera serial="cam01" model="none" viewrotation="0" ...>
          <fov_video left="0" top="0" right="1087" bottom="1919"/>
          <transform x=".." y=".." z=".." r11=".." r12=".." ... r33=".."/>
          <intrinsic focalLengthU=".." focalLengthV=".." centerPointU=".." centerPointV=".."
                     skew="0" radialDistortion1=".." radialDistortion2=".." radialDistortion3=".."
                     tangentalDistortion1=".." tangentalDistortion2=".." .../>
        </camera>
      </cameras>
    </calibration>

Conventions (cross-checked against Pose2Sim's ``calibration.py``, ``read_qca`` and
``calib_qca_fun``, and against the demo's videos):

* **Image size**: ``fov_video`` holds inclusive pixel bounds of the video window on the
  sensor, so the size is ``(right - left + 1, bottom - top + 1)``.
* **Intrinsics** are in sub-pixels, 64 per pixel: ``fx = focalLengthU / 64``,
  ``fy = focalLengthV / 64``, ``cx = centerPointU / 64 - left``,
  ``cy = centerPointV / 64 - top`` (sensor coordinates shifted into the video window).
* **Distortion** coefficients are dimensionless and used as they are:
  ``(k1, k2, p1, p2, k3) = (radialDistortion1, radialDistortion2, tangentalDistortion1,
  tangentalDistortion2, radialDistortion3)``. Pose2Sim divides them by 64 as well (and its
  ``calib_toml_to_qca`` multiplies by 64); this reader does not: a change of units cannot
  scale k1 and k2 by the same factor (it scales k_n by the 2n-th power), and fitting the
  distortion of the Pose2Sim demo cameras with K held at the file's values, on the
  checkerboard images Pose2Sim ships for them, gives k1 = -0.046 to -0.066 and
  k2 = 0.15 to 0.21: the file's raw numbers (-0.046 to -0.048, 0.13 to 0.14), not 1/64
  of them.
* **Extrinsics** are the camera's pose in the world: ``(x, y, z)`` is the camera centre in
  mm, and ``(r11, r12, r13)``, ``(r21, r22, r23)``, ``(r31, r32, r33)`` are the camera's
  axes in world coordinates, i.e. the rows of the world-to-camera rotation ``M``. The
  Qualisys camera frame has y and z opposite OpenCV's (y up the image, looking along -z),
  so ``R = diag(1, -1, -1) @ M`` and ``t = -R @ (x, y, z)``. This is Pose2Sim's conversion
  (transpose, invert, rotate by pi about x) in one step.
* **Cameras**: only video cameras are kept, by Pose2Sim's rule (``model`` contains
  "video", or is "none" or absent); marker-only cameras and cameras marked
  ``calibrated="false"`` are skipped with a warning. Names are the ``serial`` attributes
  (``cam<index>`` if absent), in file order. ``viewrotation`` other than 0 and a non-zero
  ``skew`` are rejected: their conventions are not documented.

Videos recorded at another resolution than ``fov_video`` (binning, downscaling) are
handled by ``image_size``: K is scaled by :func:`resize_camera`; distortion is unchanged.
"""

from __future__ import annotations

import dataclasses
import os
import re
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from pipeline.core.files import SceneFormatError, atomic_write, require_file
from pipeline.data.cameras import Camera, CameraRig
from pipeline.importers.calibration import (
    _build_camera,
    _check_rig,
    _image_size_arg,
    _number,
)

SUBPIXELS_PER_PIXEL = 64.0
# Qualisys camera frame -> OpenCV camera frame: y and z reversed (a rotation by pi about x).
_FLIP_YZ = np.diag([1.0, -1.0, -1.0])
_ROTATION_KEYS = tuple(f"r{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3))
_XML_DECLARATION = re.compile(rb"^\s*<\?xml[^>]*\?>")


def resize_camera(camera: Camera, width: int, height: int) -> Camera:
    """``camera`` for its image resized to ``width`` x ``height`` (e.g. ``cv2.resize``).

    Pixel centres stay pixel centres: ``u' = sx (u + 0.5) - 0.5`` with
    ``sx = width / camera.width`` (likewise v), so ``fx' = sx fx``,
    ``cx' = sx (cx + 0.5) - 0.5``. Distortion and extrinsics are unchanged.
    """
    sx, sy = width / camera.width, height / camera.height
    K = camera.K
    K_new = np.array(
        [
            [sx * K[0, 0], sx * K[0, 1], sx * (K[0, 2] + 0.5) - 0.5],
            [0.0, sy * K[1, 1], sy * (K[1, 2] + 0.5) - 0.5],
            [0.0, 0.0, 1.0],
        ]
    )
    return dataclasses.replace(camera, width=int(width), height=int(height), K=K_new)


# --------------------------------------------------------------------------- reader


def _parse(path: Path) -> ET.Element:
    data = path.read_bytes()
    try:
        return ET.fromstring(data)
    except ET.ParseError as exc:
        first_error = exc
    # QTM files are not always valid in their declared encoding (e.g. a Latin-1 user name
    # in an "ASCII" or UTF-8 file): retry on the text with unknown bytes replaced.
    text = _XML_DECLARATION.sub(b"", data).decode("utf-8", errors="replace")
    try:
        return ET.fromstring(text)
    except ET.ParseError:
        raise SceneFormatError(path, None, f"not valid XML ({first_error})") from None


def _child(element: ET.Element, tag: str, path: Path, name: str) -> ET.Element:
    child = element.find(tag)
    if child is None:
        raise SceneFormatError(path, f"{name}.{tag}", "missing")
    return child


def _attr(element: ET.Element, key: str, path: Path, field: str, default=None) -> float:
    """Attribute ``key`` of ``element`` as a finite float; errors name ``field.key``."""
    raw = element.get(key)
    if raw is None:
        if default is None:
            raise SceneFormatError(path, f"{field}.{key}", "missing")
        return float(default)
    try:
        value = float(raw)
    except ValueError:
        raise SceneFormatError(
            path, f"{field}.{key}", f"expected a number, got {raw!r:.80}"
        ) from None
    return _number(value, path, f"{field}.{key}")


def _is_video_camera(model: str | None) -> bool:
    """Pose2Sim's rule: the model names a video camera, or is "none" / absent."""
    model = (model or "none").lower()
    return "video" in model or "none" in model


def read_qualisys_calibration(
    path: str | os.PathLike, *, image_size: tuple[int, int] | None = None
) -> CameraRig:
    """Read a Qualisys ``.qca.txt`` calibration (see the module docstring for conventions).

    Args:
        path: the ``.qca.txt`` file.
        image_size: (W, H) of the videos, if they differ from the calibration's
            ``fov_video`` by a uniform scale (binning, downscaling); K is scaled to it.

    Returns:
        The video cameras, named by ``serial``, in file order, world millimetres.
    """
    path = Path(path)
    require_file(path)
    size_arg = _image_size_arg(image_size)
    root = _parse(path)
    if root.tag != "calibration":
        raise SceneFormatError(
            path, None, f"expected a Qualisys <calibration> root element, got <{root.tag}>"
        )
    elements = root.findall("cameras/camera")
    if not elements:
        raise SceneFormatError(path, "cameras", "no <camera> elements under <cameras>")
    cameras, skipped = [], []
    for i, element in enumerate(elements):
        name = element.get("serial") or f"cam{i + 1:02d}"
        model = element.get("model")
        if not _is_video_camera(model):
            skipped.append(f"{name} (model {model!r})")
            continue
        if (element.get("calibrated") or "true").strip().lower() == "false":
            skipped.append(f'{name} (calibrated="false")')
            continue
        cameras.append(_read_camera(element, name, path, size_arg))
    if skipped:
        warnings.warn(
            f"{path}: skipped cameras that are not calibrated video cameras: " + ", ".join(skipped),
            stacklevel=2,
        )
    return _check_rig(cameras, path, "cameras")


def _window_intrinsics(
    element: ET.Element, name: str, path: Path
) -> tuple[tuple[float, float], np.ndarray, np.ndarray]:
    """(width, height) of the video window, its K (3, 3) and distortion (k1, k2, p1, p2, k3)."""
    # 1. Image size: inclusive pixel bounds of the video window on the sensor.
    fov = _child(element, "fov_video", path, name)
    field = f"{name}.fov_video"
    left, top, right, bottom = (
        _attr(fov, k, path, field) for k in ("left", "top", "right", "bottom")
    )
    width, height = right - left + 1, bottom - top + 1
    if not (width.is_integer() and height.is_integer() and width > 0 and height > 0):
        raise SceneFormatError(
            path,
            field,
            f"expected whole-pixel bounds with right >= left and bottom >= top, got "
            f"left={left:g} top={top:g} right={right:g} bottom={bottom:g}",
        )

    # 2. Intrinsics: sub-pixels of the sensor -> pixels of the video window.
    intrinsic = _child(element, "intrinsic", path, name)
    field = f"{name}.intrinsic"
    fx, fy, cu, cv = (
        _attr(intrinsic, k, path, field) / SUBPIXELS_PER_PIXEL
        for k in ("focalLengthU", "focalLengthV", "centerPointU", "centerPointV")
    )
    if _attr(intrinsic, "skew", path, field, default=0) != 0:
        raise SceneFormatError(path, f"{field}.skew", "non-zero skew is not supported")
    k1, k2, p1, p2 = (
        _attr(intrinsic, k, path, field)
        for k in (
            "radialDistortion1",
            "radialDistortion2",
            "tangentalDistortion1",
            "tangentalDistortion2",
        )
    )
    k3 = _attr(intrinsic, "radialDistortion3", path, field, default=0)
    K = np.array([[fx, 0.0, cu - left], [0.0, fy, cv - top], [0.0, 0.0, 1.0]])
    return (width, height), K, np.array([k1, k2, p1, p2, k3])


def _read_camera(
    element: ET.Element, name: str, path: Path, size_arg: tuple[int, int] | None
) -> Camera:
    rotation = _attr(element, "viewrotation", path, name, default=0)
    if rotation != 0:
        raise SceneFormatError(
            path,
            f"{name}.viewrotation",
            f"view rotation {rotation:g} is not supported (only 0); rotate the calibration "
            "with the videos before converting",
        )

    # 1. Image size and 2. intrinsics, in pixels of the video window.
    (width, height), K, dist = _window_intrinsics(element, name, path)

    # 3. Extrinsics: camera pose in the world (Qualisys camera axes) -> OpenCV world-to-camera.
    transform = _child(element, "transform", path, name)
    field = f"{name}.transform"
    M = np.array([_attr(transform, k, path, field) for k in _ROTATION_KEYS]).reshape(3, 3)
    center = np.array([_attr(transform, k, path, field) for k in ("x", "y", "z")])
    camera = _build_camera(
        name=name,
        size=(int(width), int(height)),
        K=K,
        dist=dist,
        R=_FLIP_YZ @ M,
        center=center,
        source=path,
        fields={
            "K": (path, f"{name}.intrinsic"),
            "dist": (path, f"{name}.intrinsic"),
            "R": (path, f"{name}.transform (r11..r33)"),
            "t": (path, f"{name}.transform (x, y, z)"),
            "width": (path, f"{name}.fov_video"),
            "height": (path, f"{name}.fov_video"),
        },
    )
    if size_arg is None or size_arg == (camera.width, camera.height):
        return camera
    W, H = size_arg
    # A uniform scale, to within a pixel of rounding; anything else is a crop or a rotation.
    if (
        abs(W - camera.width * H / camera.height) > 1
        or abs(H - camera.height * W / camera.width) > 1
    ):
        raise SceneFormatError(
            path,
            f"{name}.fov_video",
            f"the calibrated video window is {camera.width}x{camera.height} but the images are "
            f"{W}x{H}: not a uniform scaling (cropped, padded or rotated videos?)",
        )
    return resize_camera(camera, W, H)


# --------------------------------------------------------------------------- writer


def _num(x: float) -> str:
    return repr(float(x))


def write_qualisys_calibration(rig: CameraRig, path: str | os.PathLike) -> Path:
    """Write ``rig`` as a Qualisys ``.qca.txt`` in the structure of Pose2Sim's demo files.

    Full double precision; ``model="none"`` so Pose2Sim takes the cameras as video cameras.
    Note that Pose2Sim divides the distortion coefficients by 64 when it reads them (see
    the module docstring). Qualisys has no documented skew: a camera with ``K[0, 1] != 0``
    is an error.
    """
    path = Path(path)
    root = ET.Element(
        "calibration",
        {"created": "mvviz", "source": path.name, "type": "regular", "qtm-version": "none"},
    )
    ET.SubElement(root, "results", {"std-dev": "0", "min-max-diff": "0"})
    cameras = ET.SubElement(root, "cameras")
    for cam in rig:
        if cam.K[0, 1] != 0:
            raise SceneFormatError(
                path, f"{cam.name}.intrinsic.skew", "Qualisys has no skew; K[0, 1] != 0"
            )
        element = ET.SubElement(
            cameras,
            "camera",
            {
                "active": "1",
                "avg-residual": "0",
                "model": "none",
                "point-count": "0",
                "serial": cam.name,
                "viewrotation": "0",
            },
        )
        bounds = {
            "left": "0",
            "top": "0",
            "right": str(cam.width - 1),
            "bottom": str(cam.height - 1),
        }
        for tag in ("fov_marker", "fov_marker_max", "fov_video", "fov_video_max"):
            ET.SubElement(element, tag, bounds)
        M = _FLIP_YZ @ cam.R
        transform = {k: _num(v) for k, v in zip("xyz", cam.center, strict=True)}
        transform |= {k: _num(v) for k, v in zip(_ROTATION_KEYS, M.ravel(), strict=True)}
        ET.SubElement(element, "transform", transform)
        k1, k2, p1, p2, k3 = cam.dist
        s = SUBPIXELS_PER_PIXEL
        ET.SubElement(
            element,
            "intrinsic",
            {
                "centerPointU": _num(cam.K[0, 2] * s),
                "centerPointV": _num(cam.K[1, 2] * s),
                "focalLengthU": _num(cam.K[0, 0] * s),
                "focalLengthV": _num(cam.K[1, 1] * s),
                "radialDistortion1": _num(k1),
                "radialDistortion2": _num(k2),
                "radialDistortion3": _num(k3),
                "sensorMaxU": _num(cam.width * s - 1),
                "sensorMaxV": _num(cam.height * s - 1),
                "sensorMinU": "0.0",
                "sensorMinV": "0.0",
                "skew": "0.0",
                "tangentalDistortion1": _num(p1),
                "tangentalDistortion2": _num(p2),
            },
        )
    ET.indent(root)
    text = "<?xml version='1.0' encoding='UTF-8'?>\n" + ET.tostring(root, encoding="unicode")
    with atomic_write(path, "w") as fh:
        fh.write(text + "\n")
    return path
