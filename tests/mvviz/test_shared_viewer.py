"""A viewer shared by several clients: a page that stops answering or a client that stops
reading does not hold the others back (mvviz.workers.PageAcks, StalledClients), and
bench/bench_load.py runs and writes the figures other tools read.

The clients are bench/load_clients.py's headless websocket clients (viser's protocol, as
the browser's client speaks it), in a process of their own.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np
import pytest
import viser

from bench.bench_load import Clients, main
from bench.load_clients import stalled_socket
from mvviz.workers import DaemonPool, PageAcks, StalledClients
from tests.mvviz.conftest import wait_until


class _Host:
    """What bench_load.Clients needs of an app: a server and a frame label."""

    def __init__(self) -> None:
        self.server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
        label = self.server.gui.add_markdown("frame **0** / 9")

        class _Gui:
            pass

        self.timeline = _Gui()
        self.timeline.gui = _Gui()
        self.timeline.gui.label = label


@pytest.fixture
def host():
    h = _Host()
    yield h
    h.server.stop()


def test_a_silent_page_is_waited_for_once_and_said_once(host, capsys):
    clients = Clients(host)
    try:
        clients.connect(1)
        clients.connect(1, mute=True)  # reads everything, never answers: a background tab
        wait_until(lambda: len(host.server.get_clients()) == 2, what="both clients")
        acks = PageAcks(host.server, timeout_s=30.0, grace_s=0.2)
        t0 = time.monotonic()
        assert acks.wait() == 1
        # the answering page set the pace: the mute one had a grace, not the 30 s
        assert time.monotonic() - t0 < 20.0
        assert len(acks.silent) == 1
        for _ in range(5):  # not waited for again, and its reads do not pile up
            t0 = time.monotonic()
            assert acks.wait() == 1
            assert time.monotonic() - t0 < 20.0
        assert len(acks._pending) <= 2
        acks.stop()
    finally:
        clients.quit()
    said = [line for line in capsys.readouterr().out.splitlines() if "did not apply" in line]
    assert len(said) == 1, said


def test_a_lone_slow_page_is_always_waited_for(host):
    clients = Clients(host)
    try:
        clients.connect(1, mute=True)
        wait_until(lambda: len(host.server.get_clients()) == 1, what="the client")
        acks = PageAcks(host.server, timeout_s=0.3)
        assert acks.wait() == 0
        assert acks.silent == set()  # nobody else answered: it is the one being watched
        acks.stop()
    finally:
        clients.quit()


@pytest.mark.slow
def test_a_client_that_stops_reading_is_disconnected(host, capsys):
    stalls = StalledClients(host.server, stall_s=1.0, period_s=0.1)
    assert stalls.supported, "viser's internals moved: StalledClients does nothing"
    sock = stalled_socket(f"ws://127.0.0.1:{host.server.get_port()}", viser.__version__)
    try:
        image = host.server.gui.add_image(np.zeros((8, 8, 3), np.uint8))
        rng = np.random.default_rng(0)
        deadline = time.monotonic() + 60
        while not stalls.dropped:  # fill its socket until its sender waits
            assert time.monotonic() < deadline, "the stalled client was never disconnected"
            image.image = rng.integers(0, 255, (400, 400, 3), np.uint8)
            time.sleep(0.02)
        wait_until(lambda: not host.server._websock_server._live_connections, 10, "the drop")
    finally:
        stalls.stop()
        sock.close()
    said = [line for line in capsys.readouterr().out.splitlines() if "took nothing" in line]
    assert len(said) == 1, said


def test_daemon_pool_runs_jobs_and_reports_errors():
    pool = DaemonPool(2, "test-pool")
    futs = [pool.submit(lambda x: x * 2, i) for i in range(5)]
    assert [f.result(10) for f in futs] == [0, 2, 4, 6, 8]
    bad = pool.submit(lambda: 1 / 0)
    assert isinstance(bad.exception(10), ZeroDivisionError)
    assert all(t.daemon for t in pool._threads) and len(pool._threads) <= 2
    pool.shutdown()


@pytest.mark.slow
def test_bench_load_writes_its_figures(viewer_scene, frame_store, tmp_path, monkeypatch):
    """The bench end to end on the tiny scene, a few changes: the JSON's keys and shape
    (timings are the bench's business, not a test's)."""
    scene = viewer_scene[0]
    out = tmp_path / "load.json"
    monkeypatch.setattr(sys, "argv", ["bench_load.py"])
    main([
        "--scene", str(scene.root), "--clients", "2", "--changes", "4", "--repeats", "2",
        "--interval-ms", "10", "--playback-seconds", "1", "--stalled", "--stalled-seconds",
        "1", "--soak-minutes", "0.01", "--soak-warmup-seconds", "1", "--json", str(out),
    ])  # fmt: skip
    figures = json.loads(out.read_text())
    for key in ("one_client_median_ms", "median_ms", "p95_ms", "stalled_client_rss_growth_mb"):
        assert isinstance(figures[key], float), key
    assert figures["clients"] == 2
    assert figures["disconnected"] == 0, figures["disconnect_reasons"]
    many = figures["many_clients"]
    assert many["frame_changes"] >= 4 and len(many["per_client"]) == 2 * 2
    assert {"lag_median_ms", "kb_per_change", "frames_missed"} <= set(many["per_client"][0])
    assert many["playback"]["frames_per_s"] > 0
    assert set(figures["soak"]["start"]) == {"rss_mb", "threads", "open_fds", "open_files"}
