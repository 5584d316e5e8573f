"""Background workers of the viewer: a "latest wins" slot that never queues stale work."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class LatestWins:
    """One daemon thread running ``work()`` when requested; requests made while it runs
    collapse into one more run (latest wins), so only the newest state is ever drawn.
    ``request(delay)`` asks for a later run (rate limiting). The thread ends at
    :meth:`stop` or when ``halted()`` is true at a request."""

    def __init__(
        self,
        work: Callable[[], None],
        *,
        name: str = "mvviz-render",
        halted: Callable[[], bool] = lambda: False,
    ) -> None:
        self._work, self._halted = work, halted
        self._cv = threading.Condition()
        self._pending = self._busy = self._stopped = False
        self._due: float | None = None
        self.errors: list[str] = []
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def request(self, delay: float = 0.0) -> None:
        with self._cv:
            if delay <= 0:
                self._pending = True
            else:
                due = time.monotonic() + delay
                self._due = due if self._due is None else min(self._due, due)
            self._cv.notify_all()

    def wait_idle(self, timeout: float = 10.0) -> bool:
        """Block until no run is pending, due or running (for tests and scripts)."""
        end = time.monotonic() + timeout
        with self._cv:
            while self._pending or self._busy or self._due is not None:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cv.wait(min(left, 0.05))
        return True

    def stop(self) -> None:
        with self._cv:
            self._stopped = True
            self._cv.notify_all()
        self._thread.join(timeout=5)

    def _loop(self) -> None:
        while True:
            with self._cv:
                while not self._stopped and not self._pending:
                    if self._due is not None and time.monotonic() >= self._due:
                        break
                    wait = None if self._due is None else max(self._due - time.monotonic(), 0)
                    self._cv.wait(wait)
                if self._stopped or self._halted():
                    self._stopped, self._pending, self._due = True, False, None
                    self._cv.notify_all()
                    return
                self._pending, self._due, self._busy = False, None, True
            try:
                self._work()
            except Exception as exc:  # keep the panel alive; the next request retries
                self.errors.append(f"{type(exc).__name__}: {exc}")
                print(f"mvviz view: {self._thread.name} failed: {self.errors[-1]}")
            finally:
                with self._cv:
                    self._busy = False
                    self._cv.notify_all()
