"""Parameter sweeps: ``--sweep SECTION.FIELD=V1,V2,...`` (repeatable) -> the grid.

Each value is an override in ``mvviz run --set``'s syntax (``kalman.q=50``), parsed
and checked by :meth:`pipeline.config.PipelineConfig.with_overrides`, so a sweep names
the same fields with the same types. The grid is the cartesian product of the sweeps,
in the order given; a plain grid, not Ray Tune: every point is run anyway (the report
compares them all), and Tune's search algorithms and early stopping need a single
objective and many more trials than a researcher's few values per parameter.
"""

from __future__ import annotations

import itertools

from pipeline.config import PipelineConfig
from pipeline.core.files import SceneFormatError


def parse_sweep(raw: str) -> tuple[str, list[str]]:
    """``"kalman.q=10,50"`` -> ``("kalman.q", ["10", "50"])``."""
    key, sep, values = raw.partition("=")
    key = key.strip()
    items = [v.strip() for v in values.split(",")] if sep else []
    if not key or not items or any(not v for v in items):
        raise SceneFormatError("--sweep", raw, "expected SECTION.FIELD=V1,V2,...")
    return key, items


def sweep_grid(sweeps: list[str], *, base: PipelineConfig | None = None) -> list[tuple[str, ...]]:
    """Every setting of the grid as a tuple of ``--set`` assignments (``[()]`` without
    sweeps); each assignment is checked against ``base`` (a bad field or value is a
    :class:`~pipeline.core.files.SceneFormatError` naming it, before anything runs)."""
    parsed = [parse_sweep(s) for s in sweeps]
    keys = [k for k, _ in parsed]
    if len(set(keys)) != len(keys):
        raise SceneFormatError("--sweep", ", ".join(keys), "a field is swept twice")
    base = base or PipelineConfig()
    for key, values in parsed:
        for v in values:
            try:
                base.with_overrides([f"{key}={v}"])
            except SceneFormatError as exc:
                raise SceneFormatError("--sweep", f"{key}={v}", str(exc)) from None
    grid = itertools.product(*[[f"{k}={v}" for v in values] for k, values in parsed])
    return [tuple(point) for point in grid]


def setting_slug(setting: tuple[str, ...]) -> str:
    """A file-name-safe name of a setting: ``("kalman.q=50", "association.x_mm=80")``
    -> ``kalman.q-50__association.x_mm-80`` (``default`` for the empty setting)."""
    if not setting:
        return "default"
    safe = lambda s: "".join(c if c.isalnum() or c in "._-" else "-" for c in s)  # noqa: E731
    return "__".join(safe(a.replace("=", "-")) for a in setting)
