"""Benchmark a viewer shared by a lab: N clients on one app, a client that stops reading,
and a soak.

One viewer is started as ``mvviz view SCENE`` starts it (default layers, every panel,
videos decoded in the background; default scene sample_data/shelf_synth), on a free
loopback port. Headless websocket clients (bench/load_clients.py, in one separate
process) speak viser's protocol as the browser's client does: they count the bytes they
receive, note which frame the page would show (the timeline's frame label) and answer
the viewer's localStorage reads, which playback waits for (mvviz.workers.PageAcks). In
one run:

1. one client; ``--changes`` random frame changes, one every ``--interval-ms`` (a fast
   scrub: one person drives, the others watch);
2. ``--clients`` clients; the same frame changes, then ``--playback-seconds`` of 1x
   playback;
3. with ``--stalled``: one more client that does the websocket handshake and never reads
   again (a closed laptop, a dead link) and one that reads but never answers (a tab in
   the background: the browser reads, the page does not draw); the same changes and
   playback for ``--stalled-seconds``;
4. with ``--soak-minutes S``: the other clients closed, two new ones, playback for S
   minutes: the server's RSS, threads and open file descriptors at the start (after a
   warm-up) and at the end, every 30 s between; the bench's own per-frame records are
   off meanwhile (they would be the growth it measures).

Figures: the server-side frame-change time (the viewer's own render timing, as
bench_viewer.py), median and p95, against the one-client median of the same run; each
client's lag behind the newest frame (for each frame change, from the server finishing
it to the client holding it or a newer one) and the frame changes it never saw (it got
a newer one instead); bytes per client; frames shown per second in playback; the
server's RSS over the run (sampled every 0.25 s); clients that were disconnected.

Targets: with 10 clients the median frame change <= 1.5x the one-client
median and <= 50 ms, no client disconnected; the stalled client costs the others
nothing measurable and the server's RSS stays within 100 MB of its start; a 30-minute
soak grows RSS by <= 50 MB, threads and files unchanged.

``--json OUT`` holds at least ``clients``, ``one_client_median_ms``, ``median_ms``,
``p95_ms``, ``disconnected`` (reading clients that lost their connection),
``stalled_client_rss_growth_mb`` (null without ``--stalled``).

Usage:
    python bench/bench_load.py [--scene DIR] [--clients N] [--changes M] [--interval-ms T]
        [--playback-seconds P] [--stalled [--stalled-seconds S]] [--soak-minutes S]
        [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import psutil

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.common import free_port, markdown_table, publish, write_json  # noqa: E402

MB = 1024 * 1024


# --------------------------------------------------------------------------- the server side


class Renders:
    """Every frame the viewer finished rendering: (frame, end time, server ms)."""

    def __init__(self, app) -> None:
        self._lock = threading.Lock()
        self.events: list[tuple[int, float, float]] = []
        self._app = app
        self.stop = app.subscribe(self._on_render)  # the soak records none: its own RSS

    def _on_render(self, st, reason: str) -> None:  # noqa: ARG002 - the host's signature
        ms = self._app.frame_times_ms[-1] if self._app.frame_times_ms else float("nan")
        with self._lock:
            self.events.append((int(st.frame), time.monotonic(), float(ms)))

    def take(self) -> list[tuple[int, float, float]]:
        with self._lock:
            out, self.events = self.events, []
        return out


class Sampler:
    """The server process's RSS every ``period`` seconds, from a thread."""

    def __init__(self, period: float = 0.25) -> None:
        self.proc = psutil.Process()
        self.samples: list[tuple[float, float]] = []  # (monotonic, MB)
        self.paused = False  # the soak keeps no samples (they would be its RSS growth)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, args=(period,), daemon=True)
        self._thread.start()

    def rss_mb(self) -> float:
        return self.proc.memory_info().rss / MB

    def _loop(self, period: float) -> None:
        while not self._stop.wait(period):
            if not self.paused:
                self.samples.append((time.monotonic(), self.rss_mb()))

    def between(self, t0: float, t1: float) -> list[float]:
        return [mb for t, mb in self.samples if t0 <= t <= t1]

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def process_counts(proc: psutil.Process) -> dict:
    return {
        "rss_mb": proc.memory_info().rss / MB,
        "threads": proc.num_threads(),
        "open_fds": proc.num_fds(),
        "open_files": len(proc.open_files()),
    }


def start_viewer(scene: Path):
    """The app as ``mvviz view SCENE --port P`` starts it, its videos decoded."""
    from mvviz.cli.view import add_view_options, start

    parser = argparse.ArgumentParser()
    add_view_options(parser)
    app = start(parser.parse_args([str(scene), "--port", str(free_port())]), progress=False)
    if app.frames is not None:
        assert app.frames.wait(600), "decoding the videos took too long"
    assert app.wait_idle(60)
    return app


# --------------------------------------------------------------------------- the clients


class Clients:
    """The client process (bench/load_clients.py) and its line protocol."""

    def __init__(self, app) -> None:
        import viser

        url = f"ws://127.0.0.1:{app.server.get_port()}"
        label = app.timeline.gui.label._impl.uuid
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "bench.load_clients", "--url", url,
             "--label-uuid", label, "--version", viser.__version__],
            cwd=REPO, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        )  # fmt: skip

    def ask(self, **cmd) -> dict:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(json.dumps(cmd) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"the client process ended ({self.proc.wait()})")
        return json.loads(line)

    def connect(self, n: int, mute: bool = False) -> list[int]:
        r = self.ask(cmd="connect", n=n, mute=mute)
        bad = [c for c in r["closed"] if c]
        assert not bad, f"clients could not connect: {bad}"
        return r["ids"]

    def quit(self) -> None:
        try:
            assert self.proc.stdin is not None
            self.proc.stdin.write(json.dumps({"cmd": "quit"}) + "\n")
            self.proc.stdin.flush()
            self.proc.wait(30)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()


# --------------------------------------------------------------------------- figures


def client_lag(events: list, receipts: list) -> dict:
    """For each render event (frame, end time), how long until the client held that frame
    or a newer one (s), and whether it ever held that frame itself.

    A receipt (frame, t) belongs to the latest event of that frame that had started by
    ``t``: frame numbers repeat (random changes, looping playback), times do not."""
    if not events:
        return {"lag_ms": [], "missed": 0, "never": 0}
    starts = np.array([t - ms / 1e3 for _, t, ms in events])
    owner = []
    for f, t in receipts:
        cand = [i for i, (ef, _, _) in enumerate(events) if ef == f and starts[i] <= t + 1e-3]
        owner.append(max(cand) if cand else -1)
    got = set(owner)
    reach = np.maximum.accumulate(np.array(owner)) if owner else np.array([], int)
    times = np.array([t for _, t in receipts])
    lags, never = [], 0
    for i, (_, t_end, _) in enumerate(events):
        k = np.searchsorted(reach, i)  # the first receipt holding event i or a newer one
        if k >= len(reach):
            never += 1
            continue
        lags.append(max(0.0, float(times[k] - t_end)) * 1e3)
    return {"lag_ms": lags, "missed": sum(i not in got for i in range(len(events))), "never": never}


def summarize(blocks: list, seconds: float | None = None) -> dict:
    """Server times of the render events of ``blocks`` ((events, client report, client
    ids) each) and, per client of each block's ``ids``, its lag and bytes."""
    events = [e for ev, _, _ in blocks for e in ev]
    ms = [e[2] for e in events]
    out = {
        "frame_changes": len(events),
        "median_ms": float(np.median(ms)) if ms else float("nan"),
        "p95_ms": float(np.percentile(ms, 95)) if ms else float("nan"),
    }
    if seconds:
        out["frames_per_s"] = len(events) / seconds
        gaps = np.diff([e[1] for e in events]) * 1e3 if len(events) > 1 else [float("nan")]
        out["longest_gap_ms"] = float(np.max(gaps))  # playback stood still this long
    per, pooled = [], []
    for ev, report, ids in blocks:
        for c in report["clients"]:
            if c["id"] not in ids:
                continue
            lag = client_lag(ev, [tuple(r) for r in c["frames"]])
            pooled += lag["lag_ms"]
            lags = lag["lag_ms"] or [float("nan")]
            per.append({
                "id": c["id"],
                "frame_changes": len(ev),
                "lag_median_ms": float(np.median(lags)),
                "lag_p95_ms": float(np.percentile(lags, 95)),
                "lag_max_ms": float(np.max(lags)),
                "frames_missed": lag["missed"],
                "never_caught_up": lag["never"],
                "kb_per_change": c["bytes"] / max(len(ev), 1) / 1024,
                "mb_total": c["bytes"] / MB,
                "dropped": c["dropped"],
            })  # fmt: skip
    out["per_client"] = per
    if per:
        pooled = pooled or [float("nan")]
        out["lag_median_ms"] = float(np.median(pooled))
        out["lag_p95_ms"] = float(np.percentile(pooled, 95))
        out["worst_client_lag_p95_ms"] = float(np.max([p["lag_p95_ms"] for p in per]))
        out["frames_missed_per_client"] = float(np.mean([p["frames_missed"] for p in per]))
        out["kb_per_change_per_client"] = float(np.median([p["kb_per_change"] for p in per]))
    return out


def print_phase(label: str, r: dict) -> None:
    fps = ""
    if "frames_per_s" in r:
        fps = f", {r['frames_per_s']:.1f} frames/s shown (longest gap {r['longest_gap_ms']:.0f} ms)"
    print(
        f"{label}: {r['frame_changes']} frame changes, server median {r['median_ms']:.1f} ms, "
        f"p95 {r['p95_ms']:.1f} ms{fps}; clients' lag median {r.get('lag_median_ms', 0):.0f} "
        f"ms, p95 {r.get('lag_p95_ms', 0):.0f} ms (worst client's p95 "
        f"{r.get('worst_client_lag_p95_ms', 0):.0f} ms); "
        f"{r.get('kb_per_change_per_client', 0):.1f} KB per change per client",
        flush=True,
    )


# --------------------------------------------------------------------------- phases


def random_frames(rng, n: int, num_frames: int) -> list[int]:
    """``n`` random frames, no two consecutive ones equal (each one is a change)."""
    out: list[int] = []
    while len(out) < n:
        f = int(rng.integers(0, num_frames))
        if not out or f != out[-1]:
            out.append(f)
    return out


def frame_changes(app, renders: Renders, frames: list[int], interval_s: float) -> list:
    """Go to each of ``frames``, one every ``interval_s`` (or as soon as the last one is
    drawn); the render events."""
    renders.take()
    for f in frames:
        t0 = time.monotonic()
        app.set_frame(f)
        assert app.wait_idle(60)
        time.sleep(max(0.0, interval_s - (time.monotonic() - t0)))
    time.sleep(1.0)  # the clients receive the last one
    return renders.take()


def playback(app, renders: Renders, seconds: float) -> list:
    renders.take()
    app.state.loop = True
    app.state.playing = True
    app.redraw("playing")
    time.sleep(seconds)
    app.state.playing = False
    app.redraw("playing")
    assert app.wait_idle(60)
    time.sleep(1.0)
    return renders.take()


def changes_block(app, renders, clients: Clients, ids, frames, args) -> tuple:
    """Frame changes with the clients connected: (events, client report, ids)."""
    clients.ask(cmd="mark")
    events = frame_changes(app, renders, frames, args.interval_ms / 1e3)
    return events, clients.ask(cmd="report"), list(ids)


def playback_block(app, renders, clients: Clients, ids, seconds: float) -> tuple:
    clients.ask(cmd="mark")
    events = playback(app, renders, seconds)
    return events, clients.ask(cmd="report"), list(ids)


def one_and_many(app, renders, clients: Clients, frames: list[int], args) -> tuple:
    """The frame changes with one client and with ``--clients``, in ``--repeats``
    alternating blocks (a shared machine's load drifts; each configuration gets the same
    share of it), then playback with each: (one, many, the many's client ids)."""
    first = clients.connect(1)
    one_b, many_b, ids = [], [], first
    for i, part in enumerate(np.array_split(np.array(frames), args.repeats)):
        part = [int(f) for f in part]
        if i:
            clients.ask(cmd="close", ids=ids[1:], stalled=False)
        one_b.append(changes_block(app, renders, clients, first, part, args))
        ids = first + clients.connect(args.clients - 1)
        many_b.append(changes_block(app, renders, clients, ids, part, args))
    clients.ask(cmd="close", ids=ids[1:], stalled=False)
    one, many = summarize(one_b), None
    print_phase("1 client", one)
    if args.playback_seconds:
        pb = playback_block(app, renders, clients, first, args.playback_seconds)
        one["playback"] = summarize([pb], args.playback_seconds)
        print_phase("1 client, playback", one["playback"])
    ids = first + clients.connect(args.clients - 1)
    many = summarize(many_b)
    print_phase(f"{args.clients} clients", many)
    if args.playback_seconds:
        pb = playback_block(app, renders, clients, ids, args.playback_seconds)
        many["playback"] = summarize([pb], args.playback_seconds)
        print_phase(f"{args.clients} clients, playback", many["playback"])
    return one, many, ids


def soak(app, clients: Clients, minutes: float, warmup_s: float = 20.0) -> dict:
    """Two new clients, playback for ``minutes``: process figures at start and end."""
    proc = psutil.Process()
    ids = clients.connect(2)
    app.state.loop = True
    app.state.playing = True
    app.redraw("playing")
    time.sleep(warmup_s)  # lazily started threads and pools are up
    start = process_counts(proc)
    samples = [{"s": 0.0, **start}]
    print(f"soak: 2 clients, playback for {minutes:g} min; start {start}", flush=True)
    t0 = time.monotonic()
    end_t = t0 + minutes * 60
    while time.monotonic() < end_t:
        time.sleep(min(30.0, max(0.0, end_t - time.monotonic())))
        samples.append({"s": time.monotonic() - t0, **process_counts(proc)})
    end = process_counts(proc)
    app.state.playing = False
    app.redraw("playing")
    played = app.frames_played
    report = clients.ask(cmd="report")
    closed = [c["closed"] for c in report["clients"] if c["id"] in ids and c["dropped"]]
    out = {
        "minutes": minutes,
        "start": start,
        "end": end,
        "rss_growth_mb": end["rss_mb"] - start["rss_mb"],
        "threads_change": end["threads"] - start["threads"],
        "open_fds_change": end["open_fds"] - start["open_fds"],
        "open_files_change": end["open_files"] - start["open_files"],
        "disconnected": len(closed),
        "frames_played": played,
        "samples": samples,
    }
    print(
        f"soak: end {end}; RSS {out['rss_growth_mb']:+.1f} MB, threads "
        f"{out['threads_change']:+d}, fds {out['open_fds_change']:+d}, files "
        f"{out['open_files_change']:+d}; {len(closed)} disconnected",
        flush=True,
    )
    return out


def stalled_phase(app, renders, clients, ids, frames, args, sampler, base: dict) -> dict:
    """The changes and playback again with one client that never reads and one that
    reads but never answers (a background tab)."""
    t0 = time.monotonic()
    rss0 = sampler.rss_mb()
    mute = clients.connect(1, mute=True)
    dropped_before = len(app._stalls.dropped)
    clients.ask(cmd="stall")
    out = summarize([changes_block(app, renders, clients, ids, frames, args)])
    label = "with a stalled and a mute client"
    print_phase(label, out)
    pb = playback_block(app, renders, clients, ids, args.stalled_seconds)
    out["playback"] = summarize([pb], args.stalled_seconds)
    print_phase(f"{label}, playback", out["playback"])
    t1 = time.monotonic()
    rss = sampler.between(t0, t1) or [rss0]
    out["rss_start_mb"], out["rss_max_mb"] = rss0, max(rss)
    out["rss_growth_mb"] = max(rss) - rss0
    out["stalled_dropped_by_server"] = len(app._stalls.dropped) > dropped_before
    mute_report = [c for c in clients.ask(cmd="report")["clients"] if c["id"] in mute]
    out["background_tab_disconnected"] = bool(mute_report[0]["closed"])
    out["median_ratio_vs_without"] = out["median_ms"] / base["median_ms"]
    pb, pb0 = out["playback"], base["playback"]
    out["playback_fps_ratio_vs_without"] = pb["frames_per_s"] / pb0["frames_per_s"]
    print(
        f"stalled client: others' median frame change {out['median_ratio_vs_without']:.2f}x "
        f"without it, playback {out['playback_fps_ratio_vs_without']:.2f}x the frames/s; "
        f"server RSS {rss0:.0f} -> max {max(rss):.0f} MB ({out['rss_growth_mb']:+.1f}); "
        f"{'dropped by the server' if out['stalled_dropped_by_server'] else 'still connected'}",
        flush=True,
    )
    return out


def main(argv: list[str] | None = None) -> dict:  # noqa: C901 - a script's flow
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--scene", type=Path, default=REPO / "sample_data" / "shelf_synth")
    ap.add_argument("--clients", type=int, default=10)
    ap.add_argument("--changes", type=int, default=100, help="frame changes per configuration")
    ap.add_argument("--repeats", type=int, default=3, help="alternating blocks (see above)")
    ap.add_argument("--interval-ms", type=float, default=100.0, help="one change every T ms")
    ap.add_argument("--playback-seconds", type=float, default=10.0)
    ap.add_argument("--stalled", action="store_true", help="add a client that never reads")
    ap.add_argument("--stalled-seconds", type=float, default=60.0)
    ap.add_argument("--soak-minutes", type=float, default=0.0)
    ap.add_argument("--soak-warmup-seconds", type=float, default=20.0,
                    help="playback before the soak's start figures")  # fmt: skip
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--docs", action="store_true", help="write the documentation's section")
    args = ap.parse_args(argv)
    assert args.clients >= 1 and 1 <= args.repeats <= args.changes

    app = start_viewer(args.scene)
    renders, sampler = Renders(app), Sampler()
    clients = Clients(app)
    rng = np.random.default_rng(args.seed)
    n_frames = app.state.data.num_frames
    frames = random_frames(rng, args.changes, n_frames)
    load = os.getloadavg()[0] / (os.cpu_count() or 1)
    out: dict = {"scene": args.scene.name, "clients": args.clients, "changes": args.changes,
                 "interval_ms": args.interval_ms, "load_per_cpu_at_start": load}  # fmt: skip
    print(f"{args.scene.name}: {n_frames} frames; load {load:.1f} per CPU", flush=True)
    try:
        t_start = time.monotonic()
        rss_start = sampler.rss_mb()
        frame_changes(app, renders, random_frames(rng, 10, n_frames), args.interval_ms / 1e3)
        one, many, ids = one_and_many(app, renders, clients, frames, args)
        out.update(
            one_client_median_ms=one["median_ms"],
            one_client_p95_ms=one["p95_ms"],
            median_ms=many["median_ms"],
            p95_ms=many["p95_ms"],
            median_ratio=many["median_ms"] / one["median_ms"],
            one_client=one,
            many_clients=many,
            stalled=None,
            stalled_client_rss_growth_mb=None,
        )
        if args.stalled:
            st = out["stalled"] = stalled_phase(
                app, renders, clients, ids, frames, args, sampler, many
            )
            out["stalled_client_rss_growth_mb"] = st["rss_growth_mb"]
        report = clients.ask(cmd="report")
        lost = [c for c in report["clients"] if c["dropped"]]
        out["disconnected"] = len(lost)  # reading clients, the background tab's included
        out["disconnect_reasons"] = [c["closed"] for c in lost]
        rss = sampler.between(t_start, time.monotonic())
        out["rss_mb"] = {"start": rss_start, "max": max(rss), "end": rss[-1]}
        print(
            f"{args.clients} clients: median {out['median_ms']:.1f} ms = "
            f"{out['median_ratio']:.2f}x one client ({out['one_client_median_ms']:.1f} ms), "
            f"p95 {out['p95_ms']:.1f} ms; {len(lost)} disconnected; server RSS "
            f"{rss_start:.0f} -> max {max(rss):.0f} -> {rss[-1]:.0f} MB",
            flush=True,
        )
        if args.soak_minutes > 0:
            clients.ask(cmd="close")
            renders.stop()
            sampler.paused = True
            out["soak"] = soak(app, clients, args.soak_minutes, args.soak_warmup_seconds)
    finally:
        clients.quit()
        sampler.stop()
        app.stop()
    if args.json:
        write_json(args.json, out)
    if args.docs:
        publish("bench_load", "One viewer, many clients", docs_section(out))
    return out


def docs_section(out: dict) -> str:
    """The Benchmarks page's section: frame changes with 1 and N clients, disconnects,
    the stalled client and the soak where they ran."""
    rows = [
        ["frame change, 1 client (ms)", f"{out['one_client_median_ms']:.1f}",
         f"{out['one_client_p95_ms']:.1f}"],
        [f"frame change, {out['clients']} clients (ms)", f"{out['median_ms']:.1f}",
         f"{out['p95_ms']:.1f}"],
    ]  # fmt: skip
    text = (
        f"One viewer on `{out['scene']}`, {out['changes']} frame changes a configuration "
        f"(1 client, then {out['clients']}), in alternating blocks; headless websocket "
        "clients speaking viser's protocol.\n\n"
        + markdown_table(["", "median", "p95"], rows)
        + f"\n\n{out['clients']} clients: **{out['median_ratio']:.2f}x** the one-client "
        f"median; {out['disconnected']} disconnected; server RSS {out['rss_mb']['start']:.0f} "
        f"-> max {out['rss_mb']['max']:.0f} MB."
    )
    if out.get("stalled_client_rss_growth_mb") is not None:
        text += (f" With a client that stops reading and a background tab: server RSS "
                 f"+{out['stalled_client_rss_growth_mb']:.1f} MB.")  # fmt: skip
    soak = out.get("soak")
    if soak:
        text += (
            f"\n\nSoak, {soak['minutes']:g} minutes of playback with two clients "
            f"({soak['frames_played']} frames): RSS {soak['rss_growth_mb']:+.1f} MB, threads "
            f"{soak['threads_change']:+d}, file descriptors {soak['open_fds_change']:+d}, open "
            f"files {soak['open_files_change']:+d}; {soak['disconnected']} disconnected."
        )
    return text


if __name__ == "__main__":
    main()
