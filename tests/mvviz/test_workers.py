"""mvviz.workers.yielding_to: a background job steps aside while a frame renders."""

from __future__ import annotations

import sys
import threading
import time

from mvviz.workers import yielding_to
from tests.mvviz.conftest import wait_until


def _calls(stop: threading.Event, count: list[int]) -> None:
    def step() -> None:  # a Python call: where the job may be held
        count[0] += 1

    while not stop.is_set():
        step()


def test_job_makes_no_progress_while_busy_and_resumes_after() -> None:
    busy, stop, count = threading.Event(), threading.Event(), [0]

    def job() -> None:
        with yielding_to(busy.is_set, max_wait_s=60.0):  # held as long as the test says
            _calls(stop, count)

    def settled() -> bool:  # two reads 50 ms apart agree
        before = count[0]
        time.sleep(0.05)
        return count[0] == before

    worker = threading.Thread(target=job, daemon=True)
    worker.start()
    wait_until(lambda: count[0] > 0, what="the job to run")  # while nothing renders
    busy.set()
    wait_until(settled, what="the job to be held")  # at its next call, not spinning
    held = count[0]
    time.sleep(0.2)
    assert count[0] == held
    busy.clear()
    wait_until(lambda: count[0] > held, what="the job to resume")  # once drawn
    stop.set()
    worker.join(2)
    assert not worker.is_alive()


def test_a_stuck_busy_flag_delays_each_call_at_most_max_wait() -> None:
    def job(out: list[float]) -> None:
        t0 = time.monotonic()
        with yielding_to(lambda: True, max_wait_s=0.05):
            for _ in range(3):
                len([])  # a C call: not a trace event
                abs(-1)
            _one()  # one Python call: one wait
        out.append(time.monotonic() - t0)

    out: list[float] = []
    worker = threading.Thread(target=job, args=(out,), daemon=True)
    worker.start()
    worker.join(5)
    assert out and 0.04 <= out[0] < 1.0


def _one() -> int:
    return 1


def test_previous_trace_hook_is_restored_and_other_threads_are_untouched() -> None:
    previous = sys.gettrace()
    seen: list[object] = []

    def other() -> None:
        seen.append(sys.gettrace())

    with yielding_to(lambda: False):
        inside = sys.gettrace()
        t = threading.Thread(target=other)
        t.start()
        t.join()
    assert inside is not None and inside is not previous
    assert seen == [threading.gettrace()]  # a new thread does not inherit it
    assert sys.gettrace() is previous
