"""A corpus of malformed inputs, built by the tests (nothing is shipped): at least one
bad value per declared field of scene.json, cameras.json, detections.npz, gt.npz, the
pipeline config and --set, and per field of the importers' files. Each case names the
file and the field its error must name (tests/pipeline/test_malformed_inputs.py loads
them; tests/mvviz/cli/test_errors.py runs them through the command line)."""

from __future__ import annotations

import dataclasses
import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.config import PipelineConfig, field_spec
from pipeline.data.joint_sets import COCO17
from pipeline.data.scene import SCENE_JSON, Detections, GroundTruth, write_scene
from pipeline.importers.calibration import read_voxelpose_calibration
from tests.conftest import CAMPUS_CALIB

NUM_FRAMES = 4


def write_tiny_scene(root: Path, *, smpl: bool = True) -> Path:
    """A valid scene: the 3-camera Campus rig, 4 frames, one detection per view and
    frame (with monocular SMPL columns), ground truth."""
    rig = read_voxelpose_calibration(CAMPUS_CALIB)
    rng = np.random.default_rng(0)
    n = 3 * NUM_FRAMES
    kp = np.concatenate([rng.uniform(100, 300, (n, 17, 2)), np.full((n, 17, 1), 0.9)], 2)
    mono = {}
    if smpl:
        mono = {
            "smpl_pose": np.zeros((n, 72)),
            "smpl_betas": np.zeros((n, 10)),
            "cam_weak": np.tile([1.0, 0, 0], (n, 1)),
            "bbox": np.tile([0.0, 0, 100, 100], (n, 1)),
        }
    det = Detections(
        frame=np.repeat(np.arange(NUM_FRAMES), 3), view=np.tile(np.arange(3), NUM_FRAMES),
        keypoints=kp, **mono,
    )  # fmt: skip
    gt = GroundTruth(
        frame=np.arange(NUM_FRAMES),
        person_id=np.zeros(NUM_FRAMES, int),
        joints3d=rng.normal(0, 100, (NUM_FRAMES, 24, 3)),
    )
    write_scene(root, name="tiny", fps=25, num_frames=NUM_FRAMES, joint_set=COCO17, rig=rig,
                detections=det, gt=gt)  # fmt: skip
    return root


@dataclass(frozen=True)
class Case:
    """One malformed input: ``mutate(scene_dir)`` spoils a copy of the tiny scene;
    the error must name ``file`` and ``field`` (None: the file as a whole).
    ``args``: extra command-line arguments (``--set`` / ``--config`` cases)."""

    name: str
    file: str
    field: str | None
    mutate: Callable[[Path], None] = lambda d: None
    args: tuple[str, ...] = ()


def _json_edit(name: str, edit: Callable) -> Callable[[Path], None]:
    def mutate(d: Path) -> None:
        data = json.loads((d / name).read_text())
        data = edit(data) or data
        (d / name).write_text(json.dumps(data))

    return mutate


def _npz_edit(name: str, edit: Callable[[dict], None]) -> Callable[[Path], None]:
    def mutate(d: Path) -> None:
        with np.load(d / name) as z:
            arrays = {k: z[k] for k in z.files}
        edit(arrays)
        np.savez(d / name, **arrays)

    return mutate


def _set(key, value):
    def edit(data):
        if value is _DELETE:
            del data[key]
        else:
            data[key] = value

    return edit


_DELETE = object()


def _scene_json_cases() -> list[Case]:
    out = []
    for field, spec in SCENE_JSON.items():
        for i, bad in enumerate(spec.bad_values()):
            out.append(Case(f"scene.{field}[{i}]={bad!r}", "scene.json", field,
                            _json_edit("scene.json", _set(field, bad))))  # fmt: skip
    out += [
        Case("scene.joint_set missing", "scene.json", "joint_set",
             _json_edit("scene.json", _set("joint_set", _DELETE))),
        Case("scene.references=5", "scene.json", "references",
             _json_edit("scene.json", _set("references", 5))),
        Case("scene.references.bad-name", "scene.json", "references",
             _json_edit("scene.json", _set("references", {"-x": {}}))),
        Case("scene.references.r=3", "scene.json", "references.r",
             _json_edit("scene.json", _set("references", {"r": 3}))),
        Case("scene.references.r.joint_set", "scene.json", "references.r.joint_set",
             _json_edit("scene.json", _set("references", {"r": {"joint_set": "smpl24"}}))),
        Case("scene.references.r.file missing", "r.npz", None,
             _json_edit("scene.json",
                        _set("references", {"r": {"joint_set": "coco17", "file": "r.npz"}}))),
        Case("scene.num_frames too small", "detections.npz", "frame",
             _json_edit("scene.json", _set("num_frames", 2))),
        Case("scene.json not JSON", "scene.json", None,
             lambda d: (d / "scene.json").write_text("{nope")),
        Case("scene.json a list", "scene.json", None,
             lambda d: (d / "scene.json").write_text("[1, 2]")),
        Case("scene.json NaN fps", "scene.json", "fps",
             lambda d: (d / "scene.json").write_text(
                 (d / "scene.json").read_text().replace('"fps": 25.0', '"fps": NaN'))),
    ]  # fmt: skip
    return out


def _camera_cases() -> list[Case]:
    def cam(field, value):
        def edit(data):
            if value is _DELETE:
                del data[0][field]
            else:
                data[0][field] = value

        return _json_edit("cameras.json", edit)

    bad = {
        "name": [7, "", None],
        "width": [0, -5, "640", True, 1.5, None],
        "height": [[480], {}],
        "K": [{}, [[1, 0], [0, 1]], [[0, 0, 1], [0, 0, 1], [0, 0, 1]], [["1"] * 3] * 3, "K"],
        "dist": [[0.1], ["0"] * 5, {}, [float("nan")] * 5],
        "R": [[[2, 0, 0], [0, 1, 0], [0, 0, 1]], [[1, 0, 0], [0, 1, 0], [0, 0, -1]], {}, None],
        "t": [{}, [1, 2], ["1", 2, 3], [True, 0, 0], [float("inf"), 0, 0], None],
    }
    out = [
        Case(f"cameras[0].{f}[{i}]={v!r}", "cameras.json", f"cameras[0].{f}", cam(f, v))
        for f, values in bad.items()
        for i, v in enumerate(values)
    ]
    out += [
        Case("cameras[0].t missing", "cameras.json", "cameras[0]", cam("t", _DELETE)),
        Case("cameras.json []", "cameras.json", "cameras",
             lambda d: (d / "cameras.json").write_text("[]")),
        Case("cameras.json null", "cameras.json", "cameras",
             lambda d: (d / "cameras.json").write_text("null")),
        Case("cameras[0] a number", "cameras.json", "cameras[0]",
             _json_edit("cameras.json", lambda c: [5] + c[1:])),
        Case("cameras duplicate names", "cameras.json", "cameras[].name",
             _json_edit("cameras.json", lambda c: [c[0], c[0], c[2]])),
        Case("cameras.json missing", "cameras.json", None,
             lambda d: (d / "cameras.json").unlink()),
    ]  # fmt: skip
    return out


def _array_cases(file: str, bad: dict[str, list]) -> list[Case]:
    def edit(field, value):
        def e(arrays):
            if value is _DELETE:
                del arrays[field]
            elif callable(value):
                arrays[field] = value(arrays[field] if field in arrays else None)
            else:
                arrays[field] = value

        return e

    return [
        Case(f"{file}:{f}[{i}]", file, f.split(":")[0], _npz_edit(file, edit(f.split(":")[0], v)))
        for f, values in bad.items()
        for i, v in enumerate(values)
    ]


def _detection_cases() -> list[Case]:
    n = 3 * NUM_FRAMES

    def conf(value):
        def f(kp):
            kp = kp.copy()
            kp[0, 0, 2] = value
            return kp

        return f

    def xy_nan(kp):
        kp = kp.copy()
        kp[0, 0, 0] = np.nan
        return kp

    out = _array_cases("detections.npz", {
        "frame": [_DELETE, lambda a: a + 0.5, lambda a: -a - 1, np.zeros((n, 2), int),
                  np.array(["a"] * n), lambda a: a * 0 + 100000],
        "view": [_DELETE, lambda a: a + 3, np.zeros((n, 2), int), lambda a: -a - 1],
        "keypoints": [_DELETE, lambda a: a[:, :5], lambda a: a[..., :2], np.zeros((n,)),
                      lambda a: a[:-1]],
        "smpl_pose": [_DELETE, lambda a: a[:, :10], np.full((n, 72), "x")],
        "smpl_betas": [_DELETE, lambda a: a[:, :3], lambda a: a * np.nan],
        "cam_weak": [_DELETE, lambda a: a[:, :2], lambda a: a * np.nan],
        "bbox": [_DELETE, lambda a: a[:, ::-1], lambda a: a[:, :3]],
        "mono_joints3d": [np.full((n, 5, 3), 0.0), np.full((n, 24, 3), np.inf)],
        "gt_person_id": [np.zeros(n + 1, int), np.full(n, 0.5)],
        "view_names": [np.array(["cam9", "1", "2"]), np.array([3, 4, 5])],
    })  # fmt: skip
    out += [
        Case("detections conf inf", "detections.npz", "keypoints[..., 2]",
             _npz_edit("detections.npz",
                       lambda a: a.update(keypoints=conf(np.inf)(a["keypoints"])))),
        Case("detections conf -0.1", "detections.npz", "keypoints[..., 2]",
             _npz_edit("detections.npz", lambda a: a.update(keypoints=conf(-0.1)(a["keypoints"])))),
        Case("detections conf NaN", "detections.npz", "keypoints[..., 2]",
             _npz_edit("detections.npz",
                       lambda a: a.update(keypoints=conf(np.nan)(a["keypoints"])))),
        Case("detections xy NaN with conf", "detections.npz", "keypoints[..., :2]",
             _npz_edit("detections.npz", lambda a: a.update(keypoints=xy_nan(a["keypoints"])))),
        Case("detections view_names too short", "detections.npz", "view",
             _npz_edit("detections.npz", lambda a: a.update(view_names=np.array(["0"])))),
        Case("detections.npz not a zip", "detections.npz", None,
             lambda d: (d / "detections.npz").write_bytes(b"PK\x03\x04garbage")),
        Case("detections.npz pickled object", "detections.npz", None,
             lambda d: np.savez(d / "detections.npz", frame=np.array([{}], dtype=object))),
        Case("detections.npz missing", "detections.npz", None,
             lambda d: (d / "detections.npz").unlink()),
    ]  # fmt: skip
    return out


def _gt_cases() -> list[Case]:
    m = NUM_FRAMES
    out = _array_cases("gt.npz", {
        "frame": [_DELETE, lambda a: a + 0.5, lambda a: a - 9, lambda a: a + 9, np.zeros((m, 2))],
        "person_id": [_DELETE, lambda a: a - 1, np.zeros((m, 2), int), lambda a: a * 0.5 + 0.25],
        "joints3d": [_DELETE, lambda a: a[:, :17], lambda a: a[..., :2], np.full((m, 24, 3), "x")],
        "smpl_pose": [np.zeros((m, 71))],
        "smpl_betas": [np.zeros((m, 10, 1))],
        "transl": [np.zeros((m + 1, 3))],
        "keypoints3d": [np.zeros((m, 5, 3)), np.zeros((m, 17))],
    })  # fmt: skip
    out.append(Case("gt duplicate person", "gt.npz", "person_id",
                    _npz_edit("gt.npz", lambda a: a.update(frame=a["frame"] * 0))))  # fmt: skip
    return out


def _config_cases() -> list[Case]:
    """Every config field with each value its declared type refuses, in a config file."""
    out = []

    def walk(cls, prefix, default):
        for f in dataclasses.fields(cls):
            value = getattr(default, f.name)
            if dataclasses.is_dataclass(value):
                walk(type(value), prefix + f.name + ".", value)
                continue
            spec = field_spec(cls, f.name, prefix + f.name)
            for i, bad in enumerate(spec.bad_values()):
                data: dict = {}
                node = data
                for p in prefix.split(".")[:-1]:
                    node = node.setdefault(p, {})
                node[f.name] = bad

                def mutate(d, data=data):
                    (d / "bad_config.json").write_text(json.dumps(data))

                name = f"config.{prefix}{f.name}[{i}]={bad!r}"
                args = ("--config", "{scene}/bad_config.json")
                out.append(Case(name, "bad_config.json", prefix + f.name, mutate, args))

    walk(PipelineConfig, "", PipelineConfig())
    out += [
        Case("config unknown field", "bad_config.json", "kalman.nope",
             lambda d: (d / "bad_config.json").write_text('{"kalman": {"nope": 1}}'),
             ("--config", "{scene}/bad_config.json")),
        Case("config not JSON", "bad_config.json", None,
             lambda d: (d / "bad_config.json").write_text("{"),
             ("--config", "{scene}/bad_config.json")),
        Case("config a list", "bad_config.json", None,
             lambda d: (d / "bad_config.json").write_text("[]"),
             ("--config", "{scene}/bad_config.json")),
    ]  # fmt: skip
    return out


SET_CASES = [
    ("disabled_views=5", "disabled_views"),
    ('disabled_views=["cam9"]', "disabled_views"),
    ('disabled_views="01"', "disabled_views"),
    ("disabled_views=[1]", "disabled_views"),
    ("triangulation.min_views=0", "triangulation.min_views"),
    ("triangulation.min_views=2.5", "triangulation.min_views"),
    ("fit_smpl=no", "fit_smpl"),
    ("fit_smpl=1", "fit_smpl"),
    ("kalman.q=NaN", "kalman.q"),
    ("kalman.q=-1", "kalman.q"),
    ("kalman.r=lots", "kalman.r"),
    ("kalman.model=magic", "kalman"),
    ("source=magic", "source"),
    ("kalman.nope=1", "kalman.nope"),
    ("nosection.x=1", "nosection.x"),
    ("novalue", "novalue"),
    ("association.min_confidence=2", "association.min_confidence"),
    ("smpl_fit.iters=true", "smpl_fit.iters"),
    ("pose_prior={scene}/scene.json", None),
]


def _set_cases() -> list[Case]:
    out = []
    for text, field in SET_CASES:
        file = "scene.json" if text.startswith("pose_prior") else "--set"
        out.append(Case(f"--set {text}", file, field, args=("--set", text)))
    return out


def _checkpoint_cases() -> list[Case]:
    def write(data: bytes):
        return lambda d: (d / "prior.pt").write_bytes(data)

    arg = ("--set", "pose_prior={scene}/prior.pt")
    return [
        Case("checkpoint garbage", "prior.pt", None, write(b"\x80\x04garbage"), arg),
        Case("checkpoint empty", "prior.pt", None, write(b""), arg),
        Case("checkpoint missing", "nope.pt", None, args=("--set", "pose_prior={scene}/nope.pt")),
    ]


def scene_cases() -> list[Case]:
    """Cases run on a copy of the tiny scene (``mvviz run`` / :func:`load_scene`)."""
    return (
        _scene_json_cases()
        + _camera_cases()
        + _detection_cases()
        + _gt_cases()
        + _config_cases()
        + _set_cases()
        + _checkpoint_cases()
    )


def copy_scene(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns(".mvviz"))
    return dst
