"""Background workers of the viewer: a "latest wins" slot that never queues stale work;
:class:`PageAcks`, which waits until the open pages have applied what was sent (and stops
waiting for a page that does not keep up); :class:`StalledClients`, which disconnects a
client that has stopped reading."""

from __future__ import annotations

import queue
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future
from concurrent.futures import wait as futures_wait
from contextlib import contextmanager
from typing import TypeVar

import viser

T = TypeVar("T")
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
    ``timeout_s``; once a page has answered, the others have ``grace_s`` more (or twice
    the time the first one took). A page that did not answer in time while another did
    (a tab in the background, whose page does not draw; a raw websocket client) is not
    waited for again until it answers: its read stays outstanding (one per page, never a pile of
    them), and a page that never answers is asked again at most every ``recheck_s``
    (doubling while it stays silent). It is said once in the log; it is still sent
    everything, and viser's buffer sends a slow page only the newest state. A lone slow
    page is always waited for: it is the one being watched.
    """

    def __init__(
        self,
        server: viser.ViserServer,
        *,
        timeout_s: float = 2.0,
        grace_s: float = 0.5,
        recheck_s: float = 10.0,
    ) -> None:
        self.server, self.timeout_s, self.grace_s = server, timeout_s, grace_s
        self.recheck_s = max(recheck_s, timeout_s)
        self._pool = DaemonPool(32, "mvviz-acks")
        self._pending: dict[int, Future[bool]] = {}  # client id -> its unanswered read
        self._silent: dict[int, float] = {}  # client id -> how long its next read waits
        self._told: set[int] = set()
        self._lock = threading.Lock()

    @property
    def silent(self) -> set[int]:
        """The pages playback does not wait for (they did not answer while others did)."""
        return set(self._silent)

    def wait(self) -> int:
        """Block until each page answered (at most ``timeout_s``); the pages answering."""
        t0 = time.monotonic()
        deadline = t0 + self.timeout_s
        with self._lock:
            clients = dict(self.server.get_clients())
            waiting, fresh = self._ask_all(clients)
            answered: set[int] = set()
            while waiting and (left := deadline - time.monotonic()) > 0:
                done, _ = futures_wait(list(waiting.values()), left, FIRST_COMPLETED)
                for cid, fut in list(waiting.items()):
                    if fut not in done:
                        continue
                    del waiting[cid]
                    if self._pending.get(cid) is fut:
                        del self._pending[cid]
                    ok = _answered(fut)
                    if ok and fresh.get(cid) is fut:
                        if not answered:  # the others get a grace, not the whole timeout
                            took = time.monotonic() - t0
                            deadline = min(deadline, t0 + took + max(self.grace_s, 2 * took))
                        answered.add(cid)
                    elif ok:  # it answered an older read: ask after the newest
                        fresh[cid] = waiting[cid] = self._ask(cid, clients[cid])
            if answered:  # the others did not keep up: playback goes on without them
                for cid in waiting:
                    self._silence(cid)
            return len(answered)

    def stop(self) -> None:
        self._pool.shutdown()

    def _ask_all(self, clients: dict) -> tuple[dict[int, Future[bool]], dict[int, Future[bool]]]:
        """Each page's outstanding read (a new one if it has none): those to wait for, and
        of them those asked now (after the newest messages)."""
        for cid in set(self._pending) - set(clients):  # gone: their reads fail by themselves
            del self._pending[cid]
        for cid in set(self._silent) - set(clients):
            del self._silent[cid]
        waiting, fresh = {}, {}
        for cid, client in clients.items():
            old = self._pending.get(cid)
            if old is not None and old.done():
                del self._pending[cid]
                if _answered(old) and cid in self._silent:  # caught up: waited for again
                    del self._silent[cid]
                elif cid in self._silent:  # still silent: next read waits longer
                    self._silent[cid] = min(2 * self._silent[cid], 30 * self.recheck_s)
                old = None
            if old is None:
                old = fresh[cid] = self._ask(cid, client)
            if cid not in self._silent:
                waiting[cid] = old
        return waiting, fresh

    def _ask(self, cid: int, client: viser.ClientHandle) -> Future[bool]:
        timeout = self._silent.get(cid, self.recheck_s)
        fut = self._pending[cid] = self._pool.submit(self._read, client, timeout)
        return fut

    def _silence(self, cid: int) -> None:
        self._silent.setdefault(cid, self.recheck_s)
        if cid not in self._told:
            self._told.add(cid)
            print(
                f"mvviz view: page {cid} did not apply a frame in time "
                "while others did (a tab in the background?): playback no longer waits for "
                "it until it answers; it gets only the newest state",
                flush=True,
            )

    @staticmethod
    def _read(client: viser.ClientHandle, timeout: float) -> bool:
        try:
            client.local_storage.get_item(ACK_KEY, timeout=timeout)
            return True
        except (TimeoutError, RuntimeError):  # no answer in time, or it disconnected
            return False


def _answered(fut: Future[bool]) -> bool:
    return not fut.cancelled() and fut.exception() is None and fut.result()


class DaemonPool:
    """``submit(fn, *args)`` runs on up to ``size`` daemon threads, started as needed.

    Unlike :class:`~concurrent.futures.ThreadPoolExecutor`, whose threads the interpreter
    joins at exit, a job blocked on a page that never answers does not hold the process
    after Ctrl-C."""

    def __init__(self, size: int, name: str) -> None:
        self._size, self._name = size, name
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self._idle = 0
        self._queued = 0

    def submit(self, fn: Callable[..., T], *args) -> Future[T]:
        fut: Future[T] = Future()
        with self._lock:
            self._queued += 1
            self._jobs.put((fut, fn, args))
            if self._queued > self._idle and len(self._threads) < self._size:
                name = f"{self._name}_{len(self._threads)}"
                t = threading.Thread(target=self._work, name=name, daemon=True)
                self._threads.append(t)
                t.start()
        return fut

    def shutdown(self) -> None:
        """Queued jobs are cancelled; running ones finish on their own."""
        with self._lock:
            for _ in self._threads:
                self._jobs.put(None)

    def _work(self) -> None:
        while True:
            with self._lock:
                self._idle += 1
            job = self._jobs.get()
            with self._lock:
                self._idle -= 1
                if job is not None:
                    self._queued -= 1
            if job is None:
                return
            fut, fn, args = job
            if not fut.set_running_or_notify_cancel():
                continue
            try:
                fut.set_result(fn(*args))
            except BaseException as exc:  # noqa: BLE001 - the caller reads it from the future
                fut.set_exception(exc)


class StalledClients:
    """Disconnects a client that has taken nothing for ``stall_s`` seconds.

    viser keeps the newest state in one outgoing buffer shared by all clients (an update
    replaces the pending one of the same thing) and sends each client, one window at a
    time, what it has not had yet. A client that stops reading (a closed laptop, a dead
    link) leaves its window in its connection's write buffer and its sender waiting on
    it for ever: websockets' keepalive ping waits behind the same buffer, so it never
    times out. The others are not slowed and nothing piles up for it, but the
    connection and what it holds stay. Every ``period_s`` this looks at each client's
    place in the shared buffer: one that is behind and has not moved for ``stall_s``,
    with data waiting in its write buffer, is disconnected (said once in the log); a
    page that wakes up reconnects and gets the whole current state.

    It reads viser's websocket server's internals (``_live_connections``, the broadcast
    buffer's per-client cursors); with a viser that has none, it does nothing
    (tests/mvviz/test_workers.py checks it against the installed one)."""

    def __init__(
        self, server: viser.ViserServer, *, stall_s: float = 30.0, period_s: float = 5.0
    ) -> None:
        self.stall_s = stall_s
        self.dropped: list[int] = []
        self._ws = getattr(server, "_websock_server", None)
        self._seen: dict[int, tuple[int, float]] = {}  # client id -> (cursor, since)
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._loop, args=(period_s,), name="mvviz-stalls", daemon=True
        )
        self._thread.start()

    @property
    def supported(self) -> bool:
        ws = self._ws
        buffer = getattr(ws, "_broadcast_buffer", None)
        return all(
            (
                isinstance(getattr(ws, "_live_connections", None), dict),
                getattr(ws, "_background_event_loop", None) is not None,
                isinstance(getattr(buffer, "generator_cursors", None), dict),
                hasattr(buffer, "message_counter"),
            )
        )

    def check(self, now: float | None = None) -> list[int]:
        """One look at every client; the ones disconnected now."""
        if not self.supported:
            return []
        now = time.monotonic() if now is None else now
        ws = self._ws
        buffer = ws._broadcast_buffer
        newest = buffer.message_counter - 1
        conns = dict(ws._live_connections)
        for cid in set(self._seen) - set(conns):
            del self._seen[cid]
        out = []
        for cid, conn in conns.items():
            cursor = buffer.generator_cursors.get(cid)
            transport = getattr(conn, "transport", None)
            waiting = transport.get_write_buffer_size() if transport is not None else 0
            prev = self._seen.get(cid)
            if cursor is None or cursor >= newest or not waiting:
                self._seen.pop(cid, None)  # has all there is, or is taking it
            elif prev is None or prev[0] != cursor:
                self._seen[cid] = (cursor, now)
            elif now - prev[1] >= self.stall_s and transport is not None:
                ws._background_event_loop.call_soon_threadsafe(transport.abort)
                self._seen.pop(cid, None)
                self.dropped.append(cid)
                out.append(cid)
                print(
                    f"mvviz view: client {cid} took nothing for {now - prev[1]:.0f} s (a "
                    "closed laptop, a dead link?): disconnected; its page reconnects if it "
                    "wakes up",
                    flush=True,
                )
        return out

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def _loop(self, period_s: float) -> None:
        told = False
        while not self._stop.wait(period_s):
            try:
                self.check()
            except Exception as exc:  # viser changed under us: say so once, keep serving
                if not told:
                    told = True
                    print(f"mvviz view: the stalled-client check failed: {exc}", flush=True)
