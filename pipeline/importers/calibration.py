"""Camera calibrations of other tools, read into (and written from) a native :class:`CameraRig`.

Native convention (see :mod:`pipeline.data.cameras`): world millimetres, OpenCV world-to-camera
extrinsics ``x_cam = R @ X + t``, distortion ``(k1, k2, p1, p2, k3)``.

Formats:

* **VoxelPose** json (Shelf, Campus, Panoptic-style rigs): ``{name: {R, T, fx, fy, cx, cy,
  k, p}}`` with ``x_cam = R @ (X - T)``, so ``T`` is the camera centre, in mm; ``k`` is
  (k1, k2, k3) and ``p`` is (p1, p2) in OpenCV's order. The files carry no image size.
* **EasyMocap** ``intri.yml`` / ``extri.yml`` (OpenCV FileStorage YAML): ``names``,
  ``K_<cam>``, ``dist_<cam>`` (1x5), optional ``H_<cam>`` / ``W_<cam>``; ``R_<cam>``
  (Rodrigues 3x1, what EasyMocap itself reads), ``Rot_<cam>`` (3x3) and ``T_<cam>`` (3x1)
  in METRES, ``x_cam = R @ X + T``.
* **Pose2Sim / aniposelib** ``Calib.toml``: one table per camera with ``name``,
  ``size = [w, h]``, ``matrix``, ``distortions`` (k1, k2, p1, p2 [, k3]), ``rotation``
  (Rodrigues), ``translation`` (METRES, world-to-camera), ``fisheye``; plus ``[metadata]``.

Every reader raises :class:`~pipeline.core.files.SceneFormatError` naming the file and the
field in the file's own vocabulary (``K_cam3``, ``cam_01.rotation``); every writer is
atomic. Rotations are snapped to the nearest exact rotation once validated (files store
them rounded), so the camera centre equals ``-R.T @ t`` to machine precision.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.files import SceneFormatError, atomic_write, load_toml, require_file
from pipeline.core.rotations import matrix_to_rotvec, rotvec_to_matrix
from pipeline.core.schema import check_numbers
from pipeline.core.units import MM_PER_M
from pipeline.data.cameras import Camera, CameraRig, make_camera

# VoxelPose json files carry no image size; its dataset configs hard-code it
# (e.g. ORI_IMAGE_WIDTH: 1032 / ORI_IMAGE_HEIGHT: 776 for Shelf). Known rigs are
# recognised by their intrinsics (fx, fy, cx, cy) per camera name.
_KNOWN_VOXELPOSE_RIGS: dict[str, tuple[tuple[int, int], dict[str, tuple[float, ...]]]] = {
    "Shelf": (
        (1032, 776),
        {
            "0": (1063.512085, 1071.863647, 511.738251, 350.088287),
            "1": (1097.697754, 1086.668457, 521.652161, 376.587067),
            "2": (1130.065552, 1112.470337, 566.884338, 375.212708),
            "3": (1056.162598, 1059.639648, 552.43573, 393.180389),
            "4": (1089.654175, 1080.99939, 498.32962, 359.514832),
        },
    ),
    "Campus": (
        (360, 288),
        {
            "0": (437.9852173913044, 437.9852173913044, 185.3596, 139.2537),
            "1": (430.03326086956525, 430.03326086956525, 184.0583, 130.7467),
            "2": (700.9856521739131, 700.9856521739131, 167.59475, 142.0545),
        },
    ),
}

# Top-level TOML tables Pose2Sim skips when it looks for cameras.
_POSE2SIM_NON_CAMERA_TABLES = ("metadata", "capture_volume", "charuco", "checkerboard")

# Camera names that can be used unquoted as EasyMocap YAML keys / TOML table names.
_SAFE_NAME = re.compile(r"^[A-Za-z0-9_-]+$")


# --------------------------------------------------------------------------- value checks


def _array(value, path, field: str) -> np.ndarray:
    """``value`` as a finite float array, or a SceneFormatError naming ``field``."""
    if value is None:
        raise SceneFormatError(path, field, "missing")
    check_numbers(value, path, field)  # "1" and true are not numbers
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise SceneFormatError(path, field, f"expected numbers, got {value!r:.80}") from exc
    if not np.isfinite(a).all():
        raise SceneFormatError(path, field, "contains NaN or infinity")
    return a


def _matrix(value, path, field: str, shape: tuple[int, int]) -> np.ndarray:
    a = _array(value, path, field)
    if a.shape != shape:
        raise SceneFormatError(path, field, f"expected shape {shape}, got {a.shape}")
    return a


def _vector(value, path, field: str, sizes: Sequence[int]) -> np.ndarray:
    """A vector of one of ``sizes`` values, given as (n,), (n, 1) or (1, n)."""
    a = _array(value, path, field)
    if a.ndim > 2 or a.size not in sizes or (a.ndim == 2 and min(a.shape) != 1):
        want = " or ".join(str(s) for s in sizes)
        raise SceneFormatError(
            path, field, f"expected a vector of {want} values, got shape {a.shape}"
        )
    return a.reshape(-1)


def _number(value, path, field: str, *, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise SceneFormatError(path, field, f"expected a number, got {value!r:.80}")
    x = float(value)
    if not math.isfinite(x):
        raise SceneFormatError(path, field, f"expected a finite number, got {x}")
    if positive and x <= 0:
        raise SceneFormatError(path, field, f"expected a positive number, got {x}")
    return x


def _pixels(value, path, field: str) -> int:
    """A positive integer image dimension (integral floats such as ``1088.0`` are accepted)."""
    x = _number(value, path, field, positive=True)
    if not x.is_integer():
        raise SceneFormatError(path, field, f"expected a whole number of pixels, got {x}")
    return int(x)


def _dist5(value, path, field: str) -> np.ndarray:
    """OpenCV distortion with 4, 5 or more terms -> (5,) k1 k2 p1 p2 k3 (extra terms must be 0)."""
    d = _vector(value, path, field, (4, 5, 8, 12, 14))
    if d.size > 5 and np.any(d[5:] != 0):
        raise SceneFormatError(
            path,
            field,
            f"{d.size} distortion terms with non-zero rational/prism/tilt terms; only "
            "k1 k2 p1 p2 k3 are supported",
        )
    return np.append(d[:5], [0.0] * (5 - min(d.size, 5)))


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """(3, 3) -> the closest rotation matrix in the Frobenius norm (SVD projection)."""
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _build_camera(
    *,
    name: str,
    size: tuple[int, int],
    K: np.ndarray,
    dist: np.ndarray,
    R: np.ndarray,
    t: np.ndarray | None = None,
    center: np.ndarray | None = None,
    source,
    fields: Mapping[str, tuple[os.PathLike | str, str]],
) -> Camera:
    """:func:`make_camera` with errors renamed to the file's fields, then R snapped to SO(3).

    Exactly one of ``t`` (world-to-camera translation) or ``center`` (camera centre) is given,
    in mm. ``fields`` maps make_camera's keys (``K``, ``dist``, ``R``, ``t``, ``name``, ...)
    to the (file, field) the value came from; ``source`` names the file for the others.
    """
    t_raw = t if t is not None else -R @ center
    try:
        cam = make_camera(
            name=name,
            width=size[0],
            height=size[1],
            K=K,
            dist=dist,
            R=R,
            t=t_raw,
            source=source,
            field="",
        )
    except SceneFormatError as exc:
        key = (exc.field or "").rsplit(".", 1)[-1]
        prefix = f"{exc.path}: field '{exc.field}': "
        text = str(exc)
        message = text[len(prefix) :] if text.startswith(prefix) else text
        file, field = fields.get(key, (exc.path, exc.field))
        raise SceneFormatError(file, field, message) from None
    R_exact = nearest_rotation(cam.R)
    t_exact = t_raw if t is not None else -R_exact @ center
    return dataclasses.replace(cam, R=R_exact, t=np.asarray(t_exact, float))


def _image_size_arg(image_size) -> tuple[int, int] | None:
    if image_size is None:
        return None
    if len(image_size) != 2:
        raise SceneFormatError("--image-size", None, f"expected (W, H), got {image_size!r}")
    w, h = image_size
    return _pixels(w, "--image-size", "W"), _pixels(h, "--image-size", "H")


def _check_rig(cameras: list[Camera], path, field: str) -> CameraRig:
    if not cameras:
        raise SceneFormatError(path, field, "no cameras found")
    names = [c.name for c in cameras]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise SceneFormatError(path, field, f"camera names must be unique; repeated: {dupes}")
    return CameraRig(tuple(cameras))


# --------------------------------------------------------------------------- VoxelPose


def read_voxelpose_calibration(
    path: str | os.PathLike, *, image_size: tuple[int, int] | None = None
) -> CameraRig:
    """Read a VoxelPose camera json (``calibration_shelf.json`` and friends).

    Camera names are the json keys, in file order. Image size: ``image_size`` (W, H) if
    given, else per-camera ``width`` / ``height`` keys (written by
    :func:`write_voxelpose_calibration`), else the known size of the Shelf or Campus rig
    when the intrinsics match it; otherwise an error asks for ``image_size``.
    """
    path = Path(path)
    require_file(path)
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SceneFormatError(path, None, f"not valid JSON ({exc})") from exc
    if not isinstance(data, dict) or not data:
        raise SceneFormatError(path, None, "expected a JSON object {camera name: parameters}")
    size_arg = _image_size_arg(image_size)
    known_size = _known_voxelpose_size(data)
    cameras = []
    for name, c in data.items():
        if not isinstance(c, dict):
            raise SceneFormatError(path, name, "expected an object with R, T, fx, fy, cx, cy")
        for key in ("R", "T", "fx", "fy", "cx", "cy"):
            if key not in c:
                raise SceneFormatError(path, f"{name}.{key}", "missing")
        fx, fy = (_number(c[k], path, f"{name}.{k}", positive=True) for k in ("fx", "fy"))
        cx, cy = (_number(c[k], path, f"{name}.{k}") for k in ("cx", "cy"))
        k = _vector(c.get("k", [0, 0, 0]), path, f"{name}.k", (3,))
        p = _vector(c.get("p", [0, 0]), path, f"{name}.p", (2,))
        R = _matrix(c["R"], path, f"{name}.R", (3, 3))
        T = _vector(c["T"], path, f"{name}.T", (3,))
        if size_arg is not None:
            size = size_arg
        elif "width" in c or "height" in c:
            size = (
                _pixels(c.get("width"), path, f"{name}.width"),
                _pixels(c.get("height"), path, f"{name}.height"),
            )
        elif known_size is not None:
            size = known_size
        else:
            raise SceneFormatError(
                path,
                f"{name}.width",
                "VoxelPose calibrations carry no image size and this is not the Shelf or "
                "Campus rig; pass image_size=(W, H) (mvviz convert --image-size W H)",
            )
        cameras.append(
            _build_camera(
                name=str(name),
                size=size,
                K=np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]),
                dist=np.array([k[0], k[1], p[0], p[1], k[2]]),
                R=R,
                center=T,
                source=path,
                fields={
                    "K": (path, f"{name}.fx"),
                    "dist": (path, f"{name}.k"),
                    "R": (path, f"{name}.R"),
                    "t": (path, f"{name}.T"),
                },
            )
        )
    return _check_rig(cameras, path, None)


def _known_voxelpose_size(data: dict) -> tuple[int, int] | None:
    for size, intrinsics in _KNOWN_VOXELPOSE_RIGS.values():
        if set(data) != set(intrinsics):
            continue
        try:
            same = all(
                np.allclose([data[n][k] for k in ("fx", "fy", "cx", "cy")], ref, atol=1e-3)
                for n, ref in intrinsics.items()
            )
        except (KeyError, TypeError, ValueError):
            same = False
        if same:
            return size
    return None


def write_voxelpose_calibration(rig: CameraRig, path: str | os.PathLike) -> Path:
    """Write ``rig`` as a VoxelPose camera json (plus ``width`` / ``height`` keys, which
    VoxelPose ignores and :func:`read_voxelpose_calibration` reads back).

    VoxelPose has no skew term: a camera with ``K[0, 1] != 0`` is an error.
    """
    path = Path(path)
    out = {}
    for cam in rig:
        if cam.K[0, 1] != 0:
            raise SceneFormatError(path, f"{cam.name}.fx", "VoxelPose has no skew; K[0, 1] != 0")
        k1, k2, p1, p2, k3 = (float(v) for v in cam.dist)
        out[cam.name] = {
            "R": cam.R.tolist(),
            "T": [[float(v)] for v in cam.center],
            "fx": float(cam.K[0, 0]),
            "fy": float(cam.K[1, 1]),
            "cx": float(cam.K[0, 2]),
            "cy": float(cam.K[1, 2]),
            "k": [[k1], [k2], [k3]],
            "p": [[p1], [p2]],
            "width": int(cam.width),
            "height": int(cam.height),
        }
    with atomic_write(path, "w") as fh:
        fh.write(json.dumps(out, indent=2) + "\n")
    return path


# --------------------------------------------------------------------------- EasyMocap


def _open_yaml(path: Path) -> cv2.FileStorage:
    require_file(path)
    try:
        text = path.read_text()
    except UnicodeDecodeError as exc:
        raise SceneFormatError(path, None, f"not a text file ({exc})") from exc
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError) as exc:
        detail = str(exc.__cause__ or exc).strip().splitlines()[-1][:200]
        raise SceneFormatError(path, None, f"not a readable OpenCV YAML file ({detail})") from None
    if not fs.isOpened():
        raise SceneFormatError(path, None, "not a readable OpenCV YAML file")
    return fs


def _yaml_value(fs: cv2.FileStorage, key: str, path: Path):
    """A node as a numpy array / float / str / list; None if absent."""
    node = fs.getNode(key)
    if node.empty() or node.isNone():
        return None
    return _node_value(node, path, key)


def _node_value(node: cv2.FileNode, path: Path, key: str):
    if node.isMap():
        try:
            m = node.mat()
        except cv2.error:
            rows, cols, data = node.getNode("rows"), node.getNode("cols"), node.getNode("data")
            if rows.isInt() and cols.isInt() and data.isSeq():
                message = (
                    f"an !!opencv-matrix of rows x cols = {int(rows.real())} x "
                    f"{int(cols.real())} must have that many data values, got {data.size()}"
                )
            else:
                message = "expected an !!opencv-matrix with rows, cols, dt and data"
            raise SceneFormatError(path, key, message) from None
        if m is None:
            raise SceneFormatError(path, key, "expected an !!opencv-matrix")
        return np.asarray(m, float)
    if node.isSeq():
        return [_node_value(node.at(i), path, f"{key}[{i}]") for i in range(node.size())]
    if node.isInt() or node.isReal():
        return float(node.real())
    if node.isString():
        return node.string()
    raise SceneFormatError(path, key, "unsupported YAML node")


def _yaml_names(fs: cv2.FileStorage, path: Path) -> list[str] | None:
    names = _yaml_value(fs, "names", path)
    if names is None:
        return None
    if not isinstance(names, list):
        raise SceneFormatError(path, "names", "expected a list of camera names")
    out = []
    for i, n in enumerate(names):
        if isinstance(n, float) and n.is_integer():  # an unquoted number, as EasyMocap reads it
            n = str(int(n))
        if not isinstance(n, str) or not n:
            raise SceneFormatError(path, f"names[{i}]", f"expected a camera name, got {n!r}")
        out.append(n)
    return out


def read_easymocap_calibration(
    intri_path: str | os.PathLike,
    extri_path: str | os.PathLike,
    *,
    image_size: tuple[int, int] | None = None,
) -> CameraRig:
    """Read EasyMocap's ``intri.yml`` + ``extri.yml`` (translations in metres -> mm).

    Cameras come in the order of intri's ``names``. The rotation is ``R_<cam>`` (Rodrigues,
    as EasyMocap's ``read_camera`` uses) or else ``Rot_<cam>``; if both are present they must
    agree. Image size: ``H_<cam>`` / ``W_<cam>`` if present, else ``image_size`` (W, H).
    """
    intri_path, extri_path = Path(intri_path), Path(extri_path)
    intri, extri = _open_yaml(intri_path), _open_yaml(extri_path)
    names = _yaml_names(intri, intri_path)
    if names is None:
        raise SceneFormatError(intri_path, "names", "missing (the list of camera names)")
    extri_names = _yaml_names(extri, extri_path)
    if extri_names is not None and set(names) - set(extri_names):
        raise SceneFormatError(
            extri_path,
            "names",
            f"cameras {sorted(set(names) - set(extri_names))} of {intri_path.name} are missing",
        )
    size_arg = _image_size_arg(image_size)
    cameras = []
    for cam in names:
        K = _matrix(_yaml_value(intri, f"K_{cam}", intri_path), intri_path, f"K_{cam}", (3, 3))
        dist_key = f"dist_{cam}" if not intri.getNode(f"dist_{cam}").empty() else f"D_{cam}"
        dist_value = _yaml_value(intri, dist_key, intri_path)
        if dist_value is None:
            warnings.warn(f"{intri_path}: no dist_{cam}; assuming no lens distortion", stacklevel=2)
            dist_value = np.zeros(5)
        dist = _dist5(dist_value, intri_path, dist_key)
        size = _easymocap_size(intri, intri_path, cam, size_arg)

        rvec = _yaml_value(extri, f"R_{cam}", extri_path)
        rot = _yaml_value(extri, f"Rot_{cam}", extri_path)
        if rvec is None and rot is None:
            raise SceneFormatError(extri_path, f"R_{cam}", "missing (and no Rot_ either)")
        R_field = f"R_{cam}" if rvec is not None else f"Rot_{cam}"
        if rvec is not None:
            R = rotvec_to_matrix(_vector(rvec, extri_path, f"R_{cam}", (3,)))
            if rot is not None:
                R_mat = _matrix(rot, extri_path, f"Rot_{cam}", (3, 3))
                if np.abs(R_mat - R).max() > 1e-3:
                    raise SceneFormatError(
                        extri_path,
                        f"Rot_{cam}",
                        f"disagrees with R_{cam} (max difference "
                        f"{np.abs(R_mat - R).max():.3g}); EasyMocap uses R_{cam}",
                    )
        else:
            R = _matrix(rot, extri_path, f"Rot_{cam}", (3, 3))
        T = _vector(_yaml_value(extri, f"T_{cam}", extri_path), extri_path, f"T_{cam}", (3,))
        cameras.append(
            _build_camera(
                name=cam,
                size=size,
                K=K,
                dist=dist,
                R=R,
                t=T * MM_PER_M,
                source=intri_path,
                fields={
                    "K": (intri_path, f"K_{cam}"),
                    "dist": (intri_path, dist_key),
                    "R": (extri_path, R_field),
                    "t": (extri_path, f"T_{cam}"),
                },
            )
        )
    return _check_rig(cameras, intri_path, "names")


def _easymocap_size(
    intri: cv2.FileStorage, path: Path, cam: str, size_arg: tuple[int, int] | None
) -> tuple[int, int]:
    H = _yaml_value(intri, f"H_{cam}", path)
    W = _yaml_value(intri, f"W_{cam}", path)
    if H is None and W is None:
        if size_arg is None:
            raise SceneFormatError(
                path,
                f"H_{cam}",
                f"image size missing (no H_{cam} / W_{cam}); pass image_size=(W, H) "
                "(mvviz convert --image-size W H)",
            )
        return size_arg
    if H is None or W is None:
        raise SceneFormatError(path, f"H_{cam}" if H is None else f"W_{cam}", "missing")
    size = (_pixels(W, path, f"W_{cam}"), _pixels(H, path, f"H_{cam}"))
    if size_arg is not None and size_arg != size:
        warnings.warn(
            f"{path}: camera {cam} is {size[0]}x{size[1]} in the file; ignoring image size "
            f"{size_arg[0]}x{size_arg[1]}",
            stacklevel=3,
        )
    return size


def _check_yaml_name(cam: Camera, path) -> None:
    if not _SAFE_NAME.match(cam.name):
        raise SceneFormatError(
            path, "names", f"camera name {cam.name!r} cannot be a YAML key (use [A-Za-z0-9_-])"
        )


def write_easymocap_calibration(rig: CameraRig, out_dir: str | os.PathLike) -> tuple[Path, Path]:
    """Write ``out_dir/intri.yml`` and ``out_dir/extri.yml`` (translations in metres).

    Full double precision (EasyMocap's own writer rounds to 6 decimals); both the Rodrigues
    ``R_<cam>`` and the matrix ``Rot_<cam>`` are written, and ``H_<cam>`` / ``W_<cam>``.
    """
    out_dir = Path(out_dir)
    intri_path, extri_path = out_dir / "intri.yml", out_dir / "extri.yml"
    for cam in rig:
        _check_yaml_name(cam, intri_path)
    mode = cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY
    intri, extri = cv2.FileStorage(".yml", mode), cv2.FileStorage(".yml", mode)
    for cam in rig:
        intri.write(f"K_{cam.name}", cam.K)
        intri.write(f"dist_{cam.name}", cam.dist.reshape(1, 5))
        intri.write(f"H_{cam.name}", int(cam.height))
        intri.write(f"W_{cam.name}", int(cam.width))
        extri.write(f"R_{cam.name}", matrix_to_rotvec(cam.R).reshape(3, 1))
        extri.write(f"Rot_{cam.name}", cam.R)
        extri.write(f"T_{cam.name}", (cam.t / MM_PER_M).reshape(3, 1))
    # The header and the names are written by hand: OpenCV 5 writes "%YAML 1.2" where
    # EasyMocap (and OpenCV 3) write "%YAML:1.0", and it leaves names such as "true" or
    # "null" unquoted, which would read back as a number / nothing.
    header = "%YAML:1.0\n---\nnames:\n" + "".join(f'   - "{cam.name}"\n' for cam in rig)
    intri_text, extri_text = (
        header + fs.releaseAndGetString().split("---\n", 1)[1] for fs in (intri, extri)
    )
    with atomic_write(intri_path, "w") as fi, atomic_write(extri_path, "w") as fe:
        fi.write(intri_text)
        fe.write(extri_text)
    return intri_path, extri_path


# --------------------------------------------------------------------------- Pose2Sim


def read_pose2sim_calibration(path: str | os.PathLike) -> CameraRig:
    """Read a Pose2Sim / aniposelib ``Calib.toml`` (translations in metres -> mm).

    Every top-level table except ``metadata``, ``capture_volume``, ``charuco`` and
    ``checkerboard`` is a camera, named by its ``name`` (else the table name). Fisheye
    cameras and moving / zooming cameras (per-frame arrays) are rejected.
    """
    path = Path(path)
    data = load_toml(path)
    cameras = []
    for key, c in data.items():
        if key in _POSE2SIM_NON_CAMERA_TABLES or not isinstance(c, dict):
            continue
        for k in ("size", "matrix", "distortions", "rotation", "translation"):
            if k not in c:
                raise SceneFormatError(path, f"{key}.{k}", "missing")
        name = c.get("name", key)
        if not isinstance(name, str) or not name:
            raise SceneFormatError(path, f"{key}.name", f"expected a camera name, got {name!r}")
        fisheye = c.get("fisheye", False)
        if not isinstance(fisheye, bool):
            raise SceneFormatError(path, f"{key}.fisheye", f"expected true/false, got {fisheye!r}")
        if fisheye:
            raise SceneFormatError(
                path,
                f"{key}.fisheye",
                "fisheye cameras are not supported (the native model is OpenCV's pinhole with "
                "k1 k2 p1 p2 k3); recalibrate with the pinhole model",
            )
        size = c["size"]
        if not isinstance(size, list) or len(size) != 2:
            raise SceneFormatError(path, f"{key}.size", f"expected [width, height], got {size!r}")
        wh = (_pixels(size[0], path, f"{key}.size"), _pixels(size[1], path, f"{key}.size"))
        K = _matrix(c["matrix"], path, f"{key}.matrix", (3, 3))
        dist = _dist5(c["distortions"], path, f"{key}.distortions")
        rvec = _array(c["rotation"], path, f"{key}.rotation")
        if rvec.ndim != 1:
            raise SceneFormatError(
                path,
                f"{key}.rotation",
                f"expected 3 values (Rodrigues), got shape {rvec.shape} "
                "(moving cameras are not supported)",
            )
        rvec = _vector(rvec, path, f"{key}.rotation", (3,))
        t = _vector(c["translation"], path, f"{key}.translation", (3,)) * MM_PER_M
        cameras.append(
            _build_camera(
                name=name,
                size=wh,
                K=K,
                dist=dist,
                R=rotvec_to_matrix(rvec),
                t=t,
                source=path,
                fields={
                    "K": (path, f"{key}.matrix"),
                    "dist": (path, f"{key}.distortions"),
                    "R": (path, f"{key}.rotation"),
                    "t": (path, f"{key}.translation"),
                },
            )
        )
    return _check_rig(cameras, path, None)


def _toml_table(name: str, index: int) -> str:
    """Table name for a camera: its name, as Pose2Sim writes it, unless Pose2Sim reserves it."""
    if name in _POSE2SIM_NON_CAMERA_TABLES:
        return f"cam_{index + 1:02d}"
    return name if _SAFE_NAME.match(name) else json.dumps(name)


def _toml_floats(values) -> str:
    return "[ " + ", ".join(repr(float(v)) for v in np.ravel(values)) + ",]"


def write_pose2sim_calibration(rig: CameraRig, path: str | os.PathLike) -> Path:
    """Write ``rig`` as a Pose2Sim ``Calib.toml`` (translations in metres).

    Pose2Sim stores 4 distortion terms (k1, k2, p1, p2): a non-zero k3 is dropped with a
    warning. Tables are named after the cameras, as Pose2Sim's own writer does.
    """
    path = Path(path)
    lines = []
    for i, cam in enumerate(rig):
        if cam.dist[4] != 0:
            warnings.warn(
                f"{path}: camera {cam.name} has k3 = {cam.dist[4]:.6g}; Pose2Sim stores only "
                "k1 k2 p1 p2, so k3 is dropped",
                stacklevel=2,
            )
        matrix = "[ " + ", ".join(_toml_floats(row) for row in cam.K) + ",]"
        lines += [
            f"[{_toml_table(cam.name, i)}]",
            f"name = {json.dumps(cam.name)}",
            f"size = [ {int(cam.width)}, {int(cam.height)},]",
            f"matrix = {matrix}",
            f"distortions = {_toml_floats(cam.dist[:4])}",
            f"rotation = {_toml_floats(matrix_to_rotvec(cam.R))}",
            f"translation = {_toml_floats(cam.t / MM_PER_M)}",
            "fisheye = false",
            "",
        ]
    lines += ["[metadata]", "adjusted = false", "error = 0.0", ""]
    with atomic_write(path, "w") as fh:
        fh.write("\n".join(lines))
    return path


# --------------------------------------------------------------------------- Caliscope


def read_caliscope_calibration(path: str | os.PathLike, *, require_poses: bool = True) -> CameraRig:
    """Read a Caliscope ``camera_array.toml`` (translations in metres -> mm).

    One table ``[cameras.<port>]`` per camera, named ``cam_<port>`` (as Caliscope names its
    videos): ``size = [w, h]``, ``matrix`` (K), ``distortions`` (k1 k2 p1 p2 k3),
    ``rotation`` (3x3, world to camera), ``translation`` (metres). Cameras marked
    ``ignore = true`` are skipped. Without ``require_poses`` a camera lacking ``rotation``
    / ``translation`` (intrinsics only) gets the identity pose.
    """
    path = Path(path)
    data = load_toml(path)
    tables = data.get("cameras")
    if not isinstance(tables, dict) or not tables:
        raise SceneFormatError(path, "cameras", "expected [cameras.<port>] tables")
    cameras = []
    for port, c in sorted(tables.items(), key=lambda kv: (len(kv[0]), kv[0])):
        key = f"cameras.{port}"
        if not isinstance(c, dict):
            raise SceneFormatError(path, key, "expected a table")
        if c.get("ignore", False) is True:
            continue
        needed = ("size", "matrix", "distortions") + (
            ("rotation", "translation") if require_poses else ()
        )
        for k in needed:
            if k not in c:
                raise SceneFormatError(path, f"{key}.{k}", "missing")
        size = c["size"]
        if not isinstance(size, list) or len(size) != 2:
            raise SceneFormatError(path, f"{key}.size", f"expected [width, height], got {size!r}")
        wh = (_pixels(size[0], path, f"{key}.size"), _pixels(size[1], path, f"{key}.size"))
        posed = "rotation" in c and "translation" in c
        R = _matrix(c["rotation"], path, f"{key}.rotation", (3, 3)) if posed else np.eye(3)
        t = _vector(c["translation"], path, f"{key}.translation", (3,)) if posed else np.zeros(3)
        cameras.append(
            _build_camera(
                name=f"cam_{port}",
                size=wh,
                K=_matrix(c["matrix"], path, f"{key}.matrix", (3, 3)),
                dist=_dist5(c["distortions"], path, f"{key}.distortions"),
                R=R,
                t=t * MM_PER_M,
                source=path,
                fields={
                    "K": (path, f"{key}.matrix"),
                    "dist": (path, f"{key}.distortions"),
                    "R": (path, f"{key}.rotation"),
                    "t": (path, f"{key}.translation"),
                },
            )
        )
    return _check_rig(cameras, path, "cameras")


def write_caliscope_calibration(rig: CameraRig, path: str | os.PathLike) -> Path:
    """Write ``rig`` as a Caliscope ``camera_array.toml`` (ports 0, 1, ... in rig order)."""
    path = Path(path)
    lines = []
    for port, cam in enumerate(rig):
        matrix = "[" + ", ".join(_toml_floats(row) for row in cam.K) + "]"
        rotation = "[" + ", ".join(_toml_floats(row) for row in cam.R) + "]"
        lines += [
            f"[cameras.{port}]",
            f"cam_id = {port}",
            f"size = [{int(cam.width)}, {int(cam.height)}]",
            f"matrix = {matrix}",
            f"distortions = {_toml_floats(cam.dist)}",
            f"rotation = {rotation}",
            f"translation = {_toml_floats(cam.t / MM_PER_M)}",
            "",
        ]
    with atomic_write(path, "w") as fh:
        fh.write("\n".join(lines))
    return path
