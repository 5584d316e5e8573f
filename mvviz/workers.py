"""Background workers of the viewer: a "latest wins" slot that never queues stale work,
and :class:`PageAcks`, which waits until the open pages have applied what was sent."""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import viser

ACK_KEY = "mvviz-ack"  # a localStorage key that is only ever read


YIELD_MAX_WAIT_S = 0.5  # a job waits at most this long at one call (a stuck render)


@contextmanager
def yielding_to(
    busy: Callable[[], bool], *, max_wait_s: float = YIELD_MAX_WAIT_S
) -> Iterator[None]:
    """While the block runs, this thread waits (sleeping, so without the GIL) at each
    Python function call for as long as ``busy()`` is true.

    Why: a background job in the same process as the render thread takes the GIL each
    time the render thread lets it go (a socket write, a large NumPy operation) and keeps
    it for the interpreter's switch interval (5 ms); a frame change that lets go of the
    GIL a hundred times then waits half a second on 30 ms of CPU. The job cannot see
    that from its own code, which is plain array functions; a per-thread trace hook of
    call events only (no line events: the hook returns None) is the cheapest place that
    runs often (every NumPy wrapper is a Python call). ``sys.settrace`` acts on the
    calling thread only; the previous hook (a debugger, coverage) is restored after.

    Wrap only pure computation: code that holds a lock the render thread takes (a panel's
    own lock, viser's GUI writes) would make the frame wait for the job instead.
    """

    def hook(frame, event, arg):  # noqa: ARG001 - sys.settrace's signature
        if busy():
            end = time.monotonic() + max_wait_s
            while busy() and time.monotonic() < end:
                time.sleep(0.001)
        return None

    previous = sys.gettrace()
    sys.settrace(hook)
    try:
        yield
    finally:
        sys.settrace(previous)


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


class PageAcks:
    """Waits until every open page has applied the messages sent before the call.

    viser's client applies incoming messages in order, in its render loop, and answers
    a localStorage read (``client.local_storage.get_item``) from the same loop; so the
    answer to a read queued after a frame's messages means the page has applied that
    frame. Playback waits for it before advancing, so a page that draws slower than the
    video plays skips frames instead of falling behind. One wait is at most
    ``timeout_s``; a page that did not answer in time while another did (a stuck tab, a
    raw websocket client) is not waited for again for ``skip_s``, so it cannot stall the
    others. A lone slow page is always waited for: it is the one being watched.
    """

    def __init__(
        self, server: viser.ViserServer, *, timeout_s: float = 2.0, skip_s: float = 5.0
    ) -> None:
        self.server, self.timeout_s, self.skip_s = server, timeout_s, skip_s
        self._pool = ThreadPoolExecutor(4, thread_name_prefix="mvviz-acks")
        self._silent_until: dict[int, float] = {}  # client id -> monotonic time

    def wait(self) -> int:
        """Block until each page answered (at most ``timeout_s``); the pages answering."""
        now = time.monotonic()
        clients = [
            c for cid, c in self.server.get_clients().items()
            if self._silent_until.get(cid, 0.0) <= now
        ]  # fmt: skip
        futures = [(c.client_id, self._pool.submit(self._ask, c)) for c in clients]
        ok = {cid: fut.result() for cid, fut in futures}
        for cid, answered in ok.items():
            if answered:
                self._silent_until.pop(cid, None)
            elif any(ok.values()):
                self._silent_until[cid] = time.monotonic() + self.skip_s
        return sum(ok.values())

    def stop(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)

    def _ask(self, client: viser.ClientHandle) -> bool:
        try:
            client.local_storage.get_item(ACK_KEY, timeout=self.timeout_s)
            return True
        except (TimeoutError, RuntimeError):  # no answer in time, or it disconnected
            return False
