"""Progress of the long loops (frames, optimiser iterations, epochs), one way for all.

A loop reports through ``progress``, a :data:`Progress`:

- ``False``: nothing;
- ``True``: on stderr, a tqdm bar when stderr is a terminal, else (a log file, a pipe)
  one line when the stage ends (``"associate+triangulate: 300/300 frames in 2.1 s"``)
  instead of thousands of carriage-return updates;
- a callable ``progress(stage, done, total)``: called after every step, for whoever
  shows it (the viewer's progress bars); ``stage`` names the loop.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

from tqdm import tqdm

ProgressFn = Callable[[str, int, int], None]
"""``progress(stage, done, total)``: ``done`` of ``total`` steps of ``stage`` are finished."""
Progress = bool | ProgressFn

T = TypeVar("T")


class StageBar:
    """One stage's progress: :meth:`update` after each step, :meth:`close` at the end
    (or use it as a context manager)."""

    def __init__(
        self,
        stage: str,
        total: int,
        progress: Progress,
        *,
        unit: str = "it",
        leave: bool = True,
        initial: int = 0,
    ) -> None:
        """``initial``: steps already done (e.g. frames read from a cache)."""
        self.stage, self.total, self.unit, self.n = stage, int(total), unit, int(initial)
        self._callback = progress if callable(progress) else None
        self._bar = None
        self._log = progress is True and not _is_terminal()
        if progress is True and not self._log:
            self._bar = tqdm(total=total, desc=stage, unit=unit, leave=leave, initial=initial)
        self._t0 = time.perf_counter()

    def update(self, n: int = 1) -> None:
        self.n += n
        if self._bar is not None:
            self._bar.update(n)
        if self._callback is not None:
            self._callback(self.stage, self.n, self.total)

    def set_postfix(self, **values: object) -> None:
        """Shown beside a terminal's bar only (e.g. the current loss)."""
        if self._bar is not None:
            self._bar.set_postfix(**values)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        elif self._log:
            self._log = False
            took = time.perf_counter() - self._t0
            print(
                f"{self.stage}: {self.n}/{self.total} {self.unit} in {took:.1f} s", file=sys.stderr
            )

    def __enter__(self) -> StageBar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def track(
    items: Iterable[T],
    stage: str,
    progress: Progress,
    *,
    total: int | None = None,
    unit: str = "it",
    leave: bool = True,
) -> Iterator[T]:
    """``items``, reporting each one done to ``progress`` (``total`` defaults to ``len``)."""
    n = len(items) if total is None else total  # type: ignore[arg-type]
    with StageBar(stage, n, progress, unit=unit, leave=leave) as bar:
        for item in items:
            yield item
            bar.update()


class LatestProgress:
    """A progress callback that keeps the newest report of a stage with steps (``total``
    > 0), for a thread that polls it."""

    def __init__(self) -> None:
        self.value: tuple[str, int, int] | None = None

    def __call__(self, stage: str, done: int, total: int) -> None:
        if total > 0:
            self.value = (stage, done, total)


def _is_terminal() -> bool:
    isatty = getattr(sys.stderr, "isatty", None)
    return bool(isatty and isatty())
