"""The pipeline's configuration: one frozen dataclass of per-stage parameter dataclasses,
with documented defaults, JSON round trip and ``section.field=value`` overrides (the
command line's ``--set``)."""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.association.params import AssociationParams
from pipeline.core.files import SceneFormatError, atomic_write
from pipeline.core.schema import Anything, Bool, CameraOffsets, Int, Number, Spec, Str, StrList
from pipeline.fit.types import FitParams
from pipeline.stages.kalman import KalmanParams
from pipeline.stages.proportions import ProportionParams
from pipeline.stages.stitch import StitchParams
from pipeline.stages.track import TrackingParams

SOURCES = ("keypoints", "smpl")
CONFIG_FILE = "mvviz_config.json"
"""The scene's run config, ``SCENE/mvviz_config.json``: what ``mvviz run`` and ``mvviz view``
read when no ``--config`` is given, and what the viewer's panels save into."""


@dataclass(frozen=True)
class TriangulationParams:
    min_confidence: float = 0.1
    """2D joints below this confidence are not used."""
    outlier_threshold_px: float = 20.0
    """A view whose reprojection error for a joint exceeds this is dropped, the joint re-solved."""
    min_views: int = 2


@dataclass(frozen=True)
class SyncParams:
    offsets: tuple[tuple[str, float], ...] = ()
    """Per camera its time offset in frames, ``(name, frames)`` pairs sorted by name; positive =
    that camera's frames lag the others (what ``mvviz diagnose`` reports). Its 2D is
    re-timed before association (:mod:`pipeline.stages.retime`). Written in a config file
    as ``{"cam02": 1.5}``, on the command line as ``--set sync.offsets=cam02:+1.5,cam04:-3``."""

    def by_camera(self) -> dict[str, float]:
        return dict(self.offsets)


@dataclass(frozen=True)
class PipelineConfig:
    source: str = "keypoints"
    """Which 2D joints feed association and triangulation: ``keypoints`` (the 2D
    detector, in the scene's joint set) or ``smpl`` (SMPL-24 joints restored from the
    monocular SMPL predictions)."""
    disabled_views: tuple[str, ...] = ()
    """Camera names whose detections are ignored."""
    association: AssociationParams = field(default_factory=AssociationParams)
    triangulation: TriangulationParams = field(default_factory=TriangulationParams)
    tracking: TrackingParams = field(default_factory=TrackingParams)
    stitch: StitchParams = field(default_factory=StitchParams)
    proportions: ProportionParams = field(default_factory=ProportionParams)
    kalman: KalmanParams = field(default_factory=lambda: KalmanParams(q=100.0))
    """q = 100 (mm/frame^2)^2: on the sample scene the forward filter then cuts the
    acceleration error by ~48% while lowering MPJPE (q = 200: 42%; q = 50: 53%, more lag)."""
    fit_smpl: bool = True
    """Fit SMPL bodies to the filtered tracks (step I), and correct them with the pose prior."""
    use_pose_prior: bool = True
    """Run the VAE correction (needs a prior checkpoint)."""
    pose_prior: str = ""
    """Prior checkpoint; empty = the shipped sample_data/priors/pose_vae.pt."""
    smpl_fit: FitParams = field(default_factory=FitParams)
    sync: SyncParams = field(default_factory=SyncParams)

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise ValueError(f"source must be one of {SOURCES}, got {self.source!r}")

    def to_dict(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        out["sync"]["offsets"] = self.sync.by_camera()  # {camera: frames}, as files write it
        return out

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, source: str = "<config>") -> PipelineConfig:
        return _build(cls, data, source, "")

    def with_overrides(self, assignments: list[str]) -> PipelineConfig:
        """Apply ``section.field=value`` strings, each value parsed by the field's declared
        type (:func:`parse_override`); a bad one is a SceneFormatError naming ``--set``."""
        data = self.to_dict()
        for a in assignments:
            key, sep, raw = a.partition("=")
            if not sep:
                raise SceneFormatError("--set", a, "expected SECTION.FIELD=VALUE")
            node, cls = data, PipelineConfig
            parts = key.strip().split(".")
            for p in parts[:-1]:
                section = getattr(cls(), p, None)
                if p not in node or not dataclasses.is_dataclass(section):
                    raise SceneFormatError("--set", key, f"no section {p!r}")
                node, cls = node[p], type(getattr(cls(), p))
            if parts[-1] not in node:
                raise SceneFormatError("--set", key, f"no such field; fields: {sorted(node)}")
            node[parts[-1]] = parse_override(raw, field_spec(cls, parts[-1], key))
        return PipelineConfig.from_dict(data, source="--set")

    def check_cameras(self, camera_names: list[str], *, source: str = "config") -> None:
        """``disabled_views`` names cameras of the scene (checked before any stage runs)."""
        for name, given in (
            ("disabled_views", self.disabled_views),
            ("sync.offsets", [c for c, _ in self.sync.offsets]),
        ):
            unknown = sorted(set(given) - set(camera_names))
            if unknown:
                raise SceneFormatError(
                    source,
                    name,
                    f"expected camera names of the scene {camera_names}, got unknown {unknown}",
                )


# Ranges beyond "finite and >= 0" (the rule for every other number of the config).
RANGES: dict[str, Spec] = {
    "source": Str(choices=SOURCES),
    "triangulation.min_views": Int(min=2, doc="a point needs two rays"),
    "triangulation.min_confidence": Number(ge=0, le=1),
    "triangulation.outlier_threshold_px": Number(gt=0),
    "association.min_views": Int(min=1),
    "association.min_confidence": Number(ge=0, le=1),
    "association.max_distance_mm": Number(gt=0),
    "kalman.control_gain": Number(),
    "proportions.trusted_views": Int(min=2, doc="agreement needs two views"),
    "proportions.min_track_frames": Int(min=1),
    "sync.offsets": CameraOffsets(),
}


@functools.cache
def _type_hints(cls) -> dict:
    """The evaluated annotations of ``cls`` (string annotations: ``from __future__ import
    annotations``): once per class, not once per field of every config built (~25 ms a
    config, which the batch's driver pays per scene and setting)."""
    return typing.get_type_hints(cls)


def field_spec(cls, name: str, dotted: str) -> Spec:
    """The declared type of field ``name`` of the params dataclass ``cls`` as a
    :mod:`pipeline.core.schema` spec (``dotted`` is its ``section.field`` name)."""
    hint = _type_hints(cls)[name]
    args = typing.get_args(hint)
    optional = type(None) in args
    if optional:
        hint = next(a for a in args if a is not type(None))
    if dotted in RANGES:
        return dataclasses.replace(RANGES[dotted], optional=optional)
    if hint is bool:
        return Bool(optional=optional)
    if hint is int:
        return Int(min=0, optional=optional)
    if hint is float:
        return Number(ge=0, optional=optional)
    if hint is str:
        return Str(optional=optional) if name != "pose_prior" else _AnyStr(optional=optional)
    if typing.get_origin(hint) is tuple:
        return StrList(optional=optional)
    return Anything()


@dataclasses.dataclass(frozen=True)
class _AnyStr(Str):
    """A string that may be empty (``pose_prior = ""``: the shipped checkpoint)."""

    def accepts(self, value):
        return isinstance(value, str)

    def bad_values(self):
        return [v for v in super().bad_values() if v != ""]


def parse_override(raw: str, spec: Spec):
    """The text of ``--set FIELD=TEXT`` as the field's type: ``true``/``false`` for a bool,
    a JSON number, ``null`` for an optional field, a string as written (JSON quotes
    optional), a list of names as a JSON list or comma-separated (``cam0,cam1``; empty =
    none). Checked by the spec afterwards."""
    text = raw.strip()
    if text == "null" and spec.optional:
        return None
    if isinstance(spec, StrList):
        if text.startswith("["):
            return _json_or_text(text)
        text = _json_or_text(text) if text.startswith('"') else text
        return [n.strip() for n in str(text).split(",") if n.strip()]
    if isinstance(spec, Str):
        return _json_or_text(text) if text.startswith('"') else text
    return _json_or_text(text)


def _json_or_text(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def _build(cls, data: dict, source: str, prefix: str):
    if not isinstance(data, dict):
        raise SceneFormatError(
            source, prefix.rstrip(".") or None, f"expected an object, got {data!r}"
        )
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise SceneFormatError(
            source, prefix + unknown[0], f"unknown field; known: {sorted(fields)}"
        )
    kwargs = {}
    for name, value in data.items():
        default = getattr(cls(), name)
        if dataclasses.is_dataclass(default):
            kwargs[name] = _build(type(default), value, source, f"{prefix}{name}.")
        else:
            spec = field_spec(cls, name, prefix + name)
            kwargs[name] = spec.check(value, source, prefix + name)
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise SceneFormatError(source, prefix.rstrip(".") or None, str(exc)) from exc


def load_config(path: str | os.PathLike) -> PipelineConfig:
    path = Path(path)
    if not path.is_file():
        raise SceneFormatError(path, None, "config file not found")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise SceneFormatError(path, None, f"not valid JSON ({exc})") from exc
    return PipelineConfig.from_dict(data, source=str(path))


def save_config(config: PipelineConfig, path: str | os.PathLike) -> None:
    with atomic_write(path, "w") as fh:
        fh.write(json.dumps(config.to_dict(), indent=1, sort_keys=True) + "\n")
