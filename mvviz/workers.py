"""Background workers of the viewer: a "latest wins" slot that never queues stale work."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class LatestWins:
    """One worker thread running ``work()`` whenever requested; requests made while it
    runs collapse into one more run, so only the newest state is ever drawn."""

    def __init__(self, work: Callable[[], None], *, name: str = "mvviz-render") -> None:
        self._work = work
        self.errors: list[str] = []
        self._cv = threading.Condition()
        self._pending = False
        self._busy = False
        self._stopped = False
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def request(self) -> None:
        with self._cv:
            self._pending = True
            self._cv.notify_all()

    def wait_idle(self, timeout: float = 10.0) -> bool:
        """Block until no render is pending or running (for tests and scripts)."""
        end = time.monotonic() + timeout
        with self._cv:
            while self._pending or self._busy:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cv.wait(left)
        return True

    def stop(self) -> None:
        with self._cv:
            self._stopped = True
            self._cv.notify_all()
        self._thread.join(timeout=5)

    def _loop(self) -> None:
        while True:
            with self._cv:
                while not self._pending and not self._stopped:
                    self._cv.wait()
                if self._stopped:
                    return
                self._pending, self._busy = False, True
            try:
                self._work()
            except Exception as exc:  # keep the viewer alive; the next request retries
                self.errors.append(f"{type(exc).__name__}: {exc}")
                print(f"mvviz view: {self._thread.name} failed: {self.errors[-1]}")
            finally:
                with self._cv:
                    self._busy = False
                    self._cv.notify_all()
