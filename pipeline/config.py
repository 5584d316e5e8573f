"""The pipeline's configuration: one frozen dataclass of per-stage parameter dataclasses,
with documented defaults, JSON round trip and ``section.field=value`` overrides (the
command line's ``--set``)."""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.associate import AssociationParams
from pipeline.files import SceneFormatError, atomic_write
from pipeline.kalman import KalmanParams
from pipeline.smpl_fit import FitParams
from pipeline.track import TrackingParams

SOURCES = ("keypoints", "smpl")


@dataclass(frozen=True)
class TriangulationParams:
    min_confidence: float = 0.1
    """2D joints below this confidence are not used."""
    outlier_threshold_px: float = 20.0
    """A view whose reprojection error for a joint exceeds this is dropped, the joint re-solved."""
    min_views: int = 2


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

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise ValueError(f"source must be one of {SOURCES}, got {self.source!r}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, source: str = "<config>") -> PipelineConfig:
        return _build(cls, data, source, "")

    def with_overrides(self, assignments: list[str]) -> PipelineConfig:
        """Apply ``section.field=value`` strings (value parsed as JSON, else a string)."""
        data = self.to_dict()
        for a in assignments:
            if "=" not in a:
                raise ValueError(f"override {a!r}: expected section.field=value")
            key, raw = a.split("=", 1)
            try:
                value = json.loads(raw)
            except json.JSONDecodeError:
                value = raw
            node = data
            parts = key.strip().split(".")
            for p in parts[:-1]:
                if p not in node or not isinstance(node[p], dict):
                    raise ValueError(f"override {a!r}: no section {p!r}")
                node = node[p]
            if parts[-1] not in node:
                raise ValueError(f"override {a!r}: no field {parts[-1]!r}; fields: {sorted(node)}")
            node[parts[-1]] = value
        return PipelineConfig.from_dict(data, source="--set")


def _build(cls, data: dict, source: str, prefix: str):
    if not isinstance(data, dict):
        raise SceneFormatError(source, prefix or None, f"expected an object, got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise SceneFormatError(
            source, prefix + unknown[0], f"unknown field; known: {sorted(fields)}"
        )
    kwargs = {}
    for name, value in data.items():
        default = getattr(cls(), name) if name not in ("disabled_views",) else ()
        if value is None:
            kwargs[name] = None  # e.g. kalman.q = null: the model's own default
        elif dataclasses.is_dataclass(default):
            kwargs[name] = _build(type(default), value, source, f"{prefix}{name}.")
        elif isinstance(default, tuple):
            kwargs[name] = tuple(value)
        elif isinstance(default, bool) or default is None:
            kwargs[name] = value
        elif isinstance(default, (int, float)) and not isinstance(value, (int, float)):
            raise SceneFormatError(source, prefix + name, f"expected a number, got {value!r}")
        else:
            kwargs[name] = type(default)(value) if isinstance(default, (int, float)) else value
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
