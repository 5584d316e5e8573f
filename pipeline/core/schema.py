"""Declared fields of the project's JSON inputs: each field's type, range and default,
checked where the data enters; a bad value is a
:class:`~pipeline.core.files.SceneFormatError` naming the file, the field, what was
expected and what was given.

A schema is a dict ``{field: spec}``; :func:`check_object` applies it to a parsed JSON
object and returns the checked values (defaults filled in, unknown keys kept as they
are). Each spec also lists a few values it refuses (:meth:`Spec.bad_values`): the
malformed-input tests build one bad file per field from them.

JSON has no integer/float distinction and Python's ``bool`` is an ``int``: here
``true`` is never a number, ``12.7`` is never an integer, and NaN / Infinity (which
Python's json module reads) are never a valid number.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.core.files import SceneFormatError

_MISSING = object()


def _got(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def is_number(value: Any) -> bool:
    """A JSON number (int or float, not bool), or a numpy number."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
        value, (bool, np.bool_)
    )


@dataclass(frozen=True)
class Spec:
    """One field: ``optional`` = may be null or absent (then ``default``)."""

    optional: bool = False
    default: Any = None
    doc: str = ""

    def check(self, value: Any, path: str | os.PathLike, field: str) -> Any:
        if value is None or value is _MISSING:
            if self.optional:
                return self.default
            if value is _MISSING:
                raise SceneFormatError(path, field, "missing (required field)")
        if value is None or not self.accepts(value):
            raise SceneFormatError(path, field, f"expected {self.expected()}, got {_got(value)}")
        return self.convert(value)

    def accepts(self, value: Any) -> bool:
        raise NotImplementedError

    def convert(self, value: Any) -> Any:
        return value

    def expected(self) -> str:
        raise NotImplementedError

    def bad_values(self) -> list:
        """Values this field refuses (for the malformed-input corpus)."""
        return [[], {}] + ([] if self.optional else [None])


@dataclass(frozen=True)
class Int(Spec):
    min: int | None = None
    max: int | None = None

    def accepts(self, value):
        if not is_number(value) or not math.isfinite(value) or value != int(value):
            return False
        return (self.min is None or value >= self.min) and (self.max is None or value <= self.max)

    def convert(self, value):
        return int(value)

    def expected(self):
        rng = ""
        if self.min is not None and self.max is not None:
            rng = f" in [{self.min}, {self.max}]"
        elif self.min is not None:
            rng = f" >= {self.min}"
        elif self.max is not None:
            rng = f" <= {self.max}"
        return f"an integer{rng}"

    def bad_values(self):
        out = [*super().bad_values(), "3", True, 2.5]
        if self.min is not None:
            out.append(self.min - 1)
        if self.max is not None:
            out.append(self.max + 1)
        return out


@dataclass(frozen=True)
class Number(Spec):
    """A finite number; ``gt`` / ``ge`` / ``le`` bound it."""

    gt: float | None = None
    ge: float | None = None
    le: float | None = None

    def accepts(self, value):
        if not is_number(value) or not math.isfinite(value):
            return False
        return (
            (self.gt is None or value > self.gt)
            and (self.ge is None or value >= self.ge)
            and (self.le is None or value <= self.le)
        )

    def convert(self, value):
        return float(value)

    def expected(self):
        parts = []
        if self.gt is not None:
            parts.append(f"> {self.gt:g}")
        if self.ge is not None:
            parts.append(f">= {self.ge:g}")
        if self.le is not None:
            parts.append(f"<= {self.le:g}")
        return "a finite number" + (" " + " and ".join(parts) if parts else "")

    def bad_values(self):
        out = [*super().bad_values(), "1", True, float("nan"), float("inf")]
        for bound, step in ((self.gt, 0), (self.ge, -1), (self.le, 1)):
            if bound is not None:
                out.append(bound + step)
        return out


@dataclass(frozen=True)
class Str(Spec):
    """A non-empty string, one of ``choices`` if given."""

    choices: tuple[str, ...] = ()

    def accepts(self, value):
        return (
            isinstance(value, str) and bool(value) and (not self.choices or value in self.choices)
        )

    def expected(self):
        if self.choices:
            return "one of " + ", ".join(repr(c) for c in self.choices)
        return "a non-empty string"

    def bad_values(self):
        return [*super().bad_values(), 7, "", True] + (["no-such-value"] if self.choices else [])


@dataclass(frozen=True)
class Bool(Spec):
    def accepts(self, value):
        return isinstance(value, (bool, np.bool_))

    def convert(self, value):
        return bool(value)

    def expected(self):
        return "true or false"

    def bad_values(self):
        return [*super().bad_values(), "no", 1]


@dataclass(frozen=True)
class StrList(Spec):
    """A list of non-empty strings (each one of ``choices`` if given)."""

    choices: tuple[str, ...] = ()

    def accepts(self, value):
        return isinstance(value, (list, tuple)) and all(
            isinstance(v, str) and v and (not self.choices or v in self.choices) for v in value
        )

    def convert(self, value):
        return tuple(value)

    def expected(self):
        return "a list of names" + (f" from {list(self.choices)}" if self.choices else "")

    def bad_values(self):
        return [5, "cam0", [None], {}]


@dataclass(frozen=True)
class CameraOffsets(Spec):
    """Per camera a number of frames: a JSON object ``{"cam02": 1.5}``, the command line's
    ``"cam02:+1.5,cam04:-3"`` (empty = none) or ``[["cam02", 1.5]]``; converted to
    ``(name, frames)`` pairs sorted by name. Which names the scene has is checked against
    the scene (:meth:`pipeline.config.PipelineConfig.check_cameras`)."""

    def check(self, value, path, field):
        if value is None and self.optional:
            return self.default
        pairs = self._pairs(value, path, field)
        out: dict[str, float] = {}
        for name, frames in pairs:
            if not isinstance(name, str) or not name.strip():
                raise SceneFormatError(path, field, f"expected a camera name, got {_got(name)}")
            given = frames
            if isinstance(frames, str):
                try:
                    frames = float(frames)
                except ValueError:
                    frames = None
            if not is_number(frames) or not math.isfinite(frames):
                raise SceneFormatError(
                    path, field, f"camera {name!r}: expected a number of frames, got {_got(given)}"
                )
            if name.strip() in out:
                raise SceneFormatError(path, field, f"camera {name!r} given twice")
            out[name.strip()] = float(frames)
        return tuple(sorted(out.items()))

    def _pairs(self, value, path, field) -> list:
        if isinstance(value, dict):
            return list(value.items())
        if isinstance(value, str):
            pairs = []
            for item in (t.strip() for t in value.split(",")):
                if not item:
                    continue
                name, sep, frames = item.rpartition(":")
                if not sep or not name:
                    raise SceneFormatError(
                        path, field,
                        f"expected CAMERA:FRAMES pairs separated by commas (e.g. "
                        f"cam02:+1.5,cam04:-3), got {_got(item)}",
                    )  # fmt: skip
                pairs.append((name, frames.strip()))
            return pairs
        if isinstance(value, (list, tuple)) and all(
            isinstance(p, (list, tuple)) and len(p) == 2 for p in value
        ):
            return [tuple(p) for p in value]
        raise SceneFormatError(path, field, f"expected {self.expected()}, got {_got(value)}")

    def expected(self):
        return 'per camera a number of frames ({"cam02": 1.5} or "cam02:+1.5,cam04:-3")'

    def bad_values(self):
        return [5, "cam0", "cam0:soon", {"cam0": "x"}, {"cam0": True}, [["cam0"]]]


@dataclass(frozen=True)
class Anything(Spec):
    """Checked elsewhere (e.g. a nested object with its own schema)."""

    def accepts(self, value):
        return True

    def expected(self):
        return "anything"

    def bad_values(self):
        return []


def check_object(
    data: Any, schema: dict[str, Spec], path: str | os.PathLike, prefix: str = ""
) -> dict[str, Any]:
    """``data`` (a parsed JSON object) checked against ``schema``: a dict of every declared
    field (checked, defaults filled in) plus any undeclared keys as they are."""
    if not isinstance(data, dict):
        where = prefix.rstrip(".") or None
        raise SceneFormatError(path, where, f"expected a JSON object, got {_got(data)}")
    out = dict(data)
    for name, spec in schema.items():
        out[name] = spec.check(data.get(name, _MISSING), path, prefix + name)
    return out


def check_numbers(value: Any, path: str | os.PathLike, field: str) -> None:
    """``value`` is a (nested) list of JSON numbers: no strings, booleans, nulls or
    objects (``np.asarray(..., float)`` would turn ``"1"`` and ``true`` into 1.0)."""
    stack: list[Any] = [value]
    while stack:
        v = stack.pop()
        if isinstance(v, (list, tuple)):
            stack.extend(v)
        elif isinstance(v, np.ndarray):
            if v.dtype.kind not in "fiu":
                raise SceneFormatError(path, field, f"expected numbers, got dtype {v.dtype}")
        elif not is_number(v):
            raise SceneFormatError(path, field, f"expected numbers, got {_got(v)}")


def describe(schema: dict[str, Spec]) -> list[str]:
    """One line per field: name, what it must be, its default (for docs and errors)."""
    lines = []
    for name, spec in schema.items():
        line = f"{name}: {spec.expected()}"
        if spec.optional:
            line += f" or null (default {spec.default!r})"
        lines.append(line)
    return lines
