"""Benchmark one frame change of the viewer: server time and bytes sent to the browser.

On sample_data/shelf_synth (5 cameras, 4 people, 250 frames) with every layer on and
the app's default options: video on the frustums (160 px) and in the camera panel
(400 px), 2D detections, the selected track's rays, raw / filtered / ground-truth
skeletons, trails, and the ground-truth and fitted SMPL bodies as skinned meshes; every
panel attached (the filter panel's playhead, the failure and pipeline panels). A viser
server runs on a free port; no browser is needed. Over --changes random frame changes
it reports:

- the server-side time to apply one frame change (median and p95): the viewer's own
  render timing (geometry, assigning the scene nodes, frame images, flush), and the
  CPU time of its render and image threads, which a busy machine inflates much less;
- the bytes sent per frame change: every message queued during the change (including
  other panels' updates it triggers), serialised the way viser's websocket producer
  does it for one message window (msgpack + zstd for the structure, raw binary buffers
  appended), broken down by what the message updates. With --client, a headless
  websocket client also counts the bytes it actually receives.

In the same run the meshes are then replaced by ``add_mesh_simple`` nodes that get
their full vertex arrays each frame (skinned on the server with the same bone poses),
and the figures and the ratio are printed. Targets with skinned meshes: median <= 20 ms
and <= 50 KB per frame change. Then what the options and design choices cost: every
track's rays, sharp videos (320 px frustums, 640 px panel), bones posed through viser's
per-bone setters instead of mvviz.scene.skinned.BonePoser, and the viewer alone (other
panels detached). And the same frame changes with ``--rerun`` (mvviz/export/rerun_live.py
logging into rerun's server): the frame-change time with and without it, the rerun
logging time per frame, and 1x playback with it (frames logged / dropped, lag).

With --meshes-on-off, only the frame changes with the meshes on (skinned, as above) and
off (``meshes``, ``fit_meshes`` and ``bodies_on_images`` off), alternated --repeats times
in the same run, medians and the ratio (what the meshes cost per frame change).

With --browser-playback, only 1x playback of the app as ``python app.py`` starts it
(default layers) in headless chromium (software WebGL): how far the camera panel's
picture trails the 3D view and how far the page trails the newest frame sent
(tools/playback_probe.py).

Usage:
    python bench/bench_viewer.py [--scene DIR] [--changes N] [--client] [--json FILE]
                                 [--rerun-only] [--browser-playback [--seconds S]]
                                 [--meshes-on-off [--repeats R]]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

import msgspec
import numpy as np
import viser
import viser.transforms as vtf
import zstandard

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import free_port, markdown_table, publish, write_json  # noqa: E402
from mvviz.app import ViewerApp
from mvviz.scene.geometry import GT_MESH, track_color  # noqa: E402
from mvviz.scene.images import FrameStore  # noqa: E402
from mvviz.state import ViewerState  # noqa: E402
from pipeline.body.model import load_body_model  # noqa: E402
from pipeline.config import PipelineConfig  # noqa: E402
from pipeline.core.files import CACHE_DIR  # noqa: E402
from pipeline.data.scene import load_scene  # noqa: E402
from pipeline.run.pipeline import run_or_load  # noqa: E402
from tools.chromium import CHROMIUM, close_webgl_notice, launch_chromium  # noqa: E402
from tools.playback_probe import PictureLog, measure_playback  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
TARGET_MS, TARGET_KB = 20.0, 50.0


# --------------------------------------------------------------------------- bytes


class MessageTap:
    """Records every message the server queues (wraps the websocket server's
    ``queue_message``); :meth:`window_bytes` serialises them as one window."""

    def __init__(self, server: viser.ViserServer) -> None:
        self.messages: list = []
        self._ws = server._websock_server
        self._orig = self._ws.queue_message
        self._zstd = zstandard.ZstdCompressor(level=1)  # as viser's producer

        def queue_message(message) -> None:
            self.messages.append(message)
            self._orig(message)

        self._ws.queue_message = queue_message

    def take(self) -> list:
        out, self.messages = self.messages, []
        return out

    def window_bytes(self, messages: list) -> int:
        """Bytes of one websocket frame holding ``messages`` (see
        viser.infra._infra._message_producer)."""
        buffers: list[memoryview] = []
        dicts = tuple(m.as_serializable_dict(buffers) for m in messages)
        inner = msgspec.msgpack.encode(
            {
                "messages": dicts,
                "timestampSec": time.perf_counter(),
                "binaryBufferLengths": tuple(b.nbytes for b in buffers),
            }
        )
        n = 16 + len(self._zstd.compress(inner))
        for b in buffers:
            n += (8 - n % 8) % 8 + b.nbytes
        return n

    @staticmethod
    def raw_bytes(message) -> int:
        """Uncompressed size of one message: its msgpack structure plus binary buffers."""
        buffers: list[memoryview] = []
        d = message.as_serializable_dict(buffers)
        return len(msgspec.msgpack.encode(d)) + sum(b.nbytes for b in buffers)


def is_mesh(message) -> bool:
    name = getattr(message, "name", "")
    return isinstance(name, str) and name.startswith(("/world/meshes/", "/bench/"))


def category(message, gui_names: dict[str, str]) -> str:
    """What a message updates, for the breakdown."""
    name = getattr(message, "name", None)
    if is_mesh(message):
        return f"meshes ({type(message).__name__})"
    if isinstance(name, str) and name.startswith("/world/"):
        parts = name.split("/")
        if parts[2] == "cameras":
            return "frustum images" if parts[-1] == "frustum" else "cameras"
        return f"skeletons/{parts[3]}" if parts[2] == "skeletons" else parts[2]
    uuid = getattr(message, "uuid", None)
    if uuid is not None:
        return gui_names.get(uuid, "gui (other)")
    return type(message).__name__


def gui_names(app: ViewerApp) -> dict[str, str]:
    """uuid -> "panel.field" of every GUI handle in the app's panel dataclasses."""
    names = {}
    for attr, panel in vars(app).items():
        panel = getattr(panel, "gui", panel)  # controllers keep their handles in .gui
        if not dataclasses.is_dataclass(panel):
            continue
        for f in dataclasses.fields(panel):
            impl = getattr(getattr(panel, f.name), "_impl", None)
            if impl is not None and hasattr(impl, "uuid"):
                names[impl.uuid] = f"{attr}.{f.name}"
    return names


class WireClient:
    """A headless websocket client counting the bytes it receives (--client)."""

    def __init__(self, url: str) -> None:
        from websockets.sync.client import connect  # optional tool

        self.bytes = 0
        self._ws = connect(
            url.replace("http", "ws"),
            subprotocols=[f"viser-v{viser.__version__}"],
            max_size=None,
        )
        self._thread = threading.Thread(target=self._recv, daemon=True)
        self._thread.start()

    def _recv(self) -> None:
        try:
            for msg in self._ws:
                self.bytes += len(msg)
        except Exception:
            pass

    def close(self) -> None:
        self._ws.close()


# --------------------------------------------------------------------------- full-vertex mode


def lbs_vertices(bodies, i: int, frame: int) -> np.ndarray:
    """(V, 3) float32 vertices of body ``i`` at ``frame``: the browser's skinning
    (``T_world_bone(t) @ T_world_bone(bind)^-1``) done on the server."""
    R = vtf.SO3(bodies.bone_wxyz[i, frame]).as_matrix().astype(np.float32)  # (24, 3, 3)
    p = bodies.bone_position[i, frame].astype(np.float32)  # (24, 3)
    t = p - np.einsum("bij,bj->bi", R, bodies.rest_joints[i].astype(np.float32))
    w = bodies.weights.astype(np.float32)  # (V, 24)
    M = (w @ R.reshape(24, 9)).reshape(-1, 3, 3)  # (V, 3, 3)
    return np.einsum("vij,vj->vi", M, bodies.vertices[i].astype(np.float32)) + w @ t


def use_full_vertex_meshes(app: ViewerApp) -> float:
    """Replace the skinned meshes by simple meshes updated with full vertices in every
    frame change (inside the viewer's timed render). Returns their vertex count."""
    layers, data, scene = app.layers, app.state.data, app.server.scene
    bodies = [(data.bodies, layers.meshes, "gt"), (data.fit_bodies, layers.fit_meshes, "fit")]
    simple = []
    with app.server.atomic():
        for b, store, kind in bodies:
            if b is None:
                continue
            for pid, handle in store.items():
                handle.visible = False
                i = list(b.ids).index(pid)
                color = GT_MESH if kind == "gt" else tuple(int(c) for c in track_color(pid))
                h = scene.add_mesh_simple(
                    f"/bench/{kind}/{pid}", b.vertices[i], b.faces, color=color,
                    cast_shadow=False, receive_shadow=False,
                )  # fmt: skip
                simple.append((b, i, h))
            store.clear()  # the viewer no longer poses the skinned ones
    apply = layers.apply

    def apply_full(geom, selection) -> None:
        apply(geom, selection)
        for b, i, h in simple:
            if b.present[i, geom.frame]:
                h.vertices = lbs_vertices(b, i, geom.frame)
                h.visible = True
            else:
                h.visible = False

    layers.apply = apply_full
    return float(sum(b.vertices.shape[1] for b, _, _ in simple))


def use_public_bone_setters(app: ViewerApp) -> None:
    """Pose the skinned meshes through viser's per-bone setters (``bone.wxyz = ...``)
    instead of :class:`mvviz.scene.skinned.BonePoser`'s bulk path: what that path saves."""
    app.layers.fast_bones = False
    app.layers.bone_posers.clear()


def rerun_overhead(start, changes: np.ndarray, warm: np.ndarray) -> dict:
    """The same frame changes in one app without, with and again without ``--rerun``'s
    live logging (mvviz/export/rerun_live.py into a rerun server), then 5 s of 1x playback with
    it: what the logging adds to a frame change and whether it keeps up."""
    from mvviz.export.rerun_live import LiveRerun, RerunWebServer

    app, tap = start()
    server = RerunWebServer(web_port=free_port())
    try:
        measure(app, tap, warm, None)
        before = measure(app, tap, changes, None)
        live = LiveRerun(app, server=server)
        assert live.wait_idle(120)
        measure(app, tap, warm, None)
        t0 = time.perf_counter()
        with_rr = measure(app, tap, changes, None)
        took = time.perf_counter() - t0
        assert live.wait_idle(60)
        logged, dropped, log_ms = live.logged, live.dropped, live.log_ms
        n = app.state.data.num_frames
        app.state.speed, app.state.playing = 1.0, True
        app._on_change("playing")
        f0, t1, l0, d0 = app.state.frame, time.perf_counter(), live.logged, live.dropped
        time.sleep(5.0)
        app.state.playing = False
        app._on_change("playing")
        shown = (app.state.frame - f0) % n
        lag = (app.state.frame - (live.last_frame or 0)) % n
        playback = {
            "seconds": time.perf_counter() - t1, "shown": int(shown),
            "logged": live.logged - l0, "dropped": live.dropped - d0, "lag_frames": int(lag),
        }  # fmt: skip
        live.close()
        after = measure(app, tap, changes, None)
    finally:
        app.stop()
        server.stop()
    without = float(np.mean([before["median_ms"], after["median_ms"]]))
    without_cpu = float(np.mean([before["median_cpu_ms"], after["median_cpu_ms"]]))
    r = {
        "without_ms": [before["median_ms"], after["median_ms"]],
        "with_ms": with_rr["median_ms"], "with_p95_ms": with_rr["p95_ms"],
        "overhead_ms": with_rr["median_ms"] - without,
        "overhead_cpu_ms": with_rr["median_cpu_ms"] - without_cpu,
        "frames_logged": logged, "frames_dropped": dropped, "log_ms_last": log_ms,
        "seconds": took, "playback_1x": playback,
    }  # fmt: skip
    print(
        f"--rerun, same app and frame changes: median {before['median_ms']:.1f} ms without, "
        f"{with_rr['median_ms']:.1f} ms with (p95 {with_rr['p95_ms']:.1f}), "
        f"{after['median_ms']:.1f} ms without again: {r['overhead_ms']:+.1f} ms "
        f"(CPU {r['overhead_cpu_ms']:+.1f} ms); {logged} frames logged, {dropped} dropped; "
        f"1x playback 5 s: {shown} frames shown, {playback['logged']} logged, "
        f"{playback['dropped']} dropped, {lag} behind at the end"
    )
    return r


def browser_playback(scene, results, model, frames, seconds: float) -> dict:
    """1x playback of the default app in headless chromium: the page's lag."""
    from playwright.sync_api import sync_playwright  # dev extra

    state = ViewerState.create(scene, results, model)
    app = ViewerApp(state, host="127.0.0.1", port=free_port(), frames=frames, model=model)
    assert app.wait_idle(60)
    log = PictureLog(app)
    try:
        with sync_playwright() as pw:
            browser = launch_chromium(pw)
            page = browser.new_page(viewport={"width": 1400, "height": 860})
            page.goto(app.url)
            page.wait_for_selector("canvas", timeout=60_000)
            close_webgl_notice(page)
            page.wait_for_timeout(3000)  # the initial scene
            lag = measure_playback(app, page, log, seconds=seconds)
            browser.close()
    finally:
        app.stop()
    print(f"1x playback in headless chromium: {lag.summary()}")
    med = lambda x: float(np.median(x)) if x.size else None  # noqa: E731
    top = lambda x: int(x.max()) if x.size else None  # noqa: E731
    return {
        "samples": lag.samples, "seconds": lag.seconds, "frames_played": lag.frames_advanced,
        "frames_sent": lag.renders,
        "image_lag_median": med(lag.image_lag), "image_lag_max": top(lag.image_lag),
        "sent_lag_median": med(lag.sent_lag), "sent_lag_max": top(lag.sent_lag),
        "label_lag_median": med(lag.label_lag), "label_lag_max": top(lag.label_lag),
    }  # fmt: skip


# --------------------------------------------------------------------------- runs


def measure(app: ViewerApp, tap: MessageTap, frames: np.ndarray, client: WireClient | None):
    """Time and bytes of each frame change to ``frames``."""
    names = gui_names(app)
    ms, cpu, wire, meshes, by_cat = [], [], [], [], defaultdict(float)
    client_bytes = 0
    for f in frames:
        tap.take()
        c0 = client.bytes if client else 0
        app.frame_times_ms.clear()
        app.bench_cpu_ms.clear()
        app.set_frame(int(f))
        assert app.wait_idle(30)
        time.sleep(0.01)  # callbacks after the render (other panels' status lines)
        msgs = tap.take()
        ms.append(app.frame_times_ms[0])
        cpu.append(app.bench_cpu_ms[0])
        wire.append(tap.window_bytes(msgs))
        meshes.append(tap.window_bytes([m for m in msgs if is_mesh(m)]))
        for m in msgs:
            by_cat[category(m, names)] += tap.raw_bytes(m)
        if client:
            time.sleep(0.05)
            client_bytes += client.bytes - c0
    n = len(frames)
    return {
        "median_ms": float(np.median(ms)),
        "p95_ms": float(np.percentile(ms, 95)),
        "median_cpu_ms": float(np.median(cpu)),
        "p95_cpu_ms": float(np.percentile(cpu, 95)),
        "median_kb": float(np.median(wire)) / 1024,
        "mean_kb": float(np.mean(wire)) / 1024,
        "meshes_kb": float(np.median(meshes)) / 1024,
        "client_kb": client_bytes / n / 1024 if client else None,
        "breakdown_kb": {k: v / n / 1024 for k, v in sorted(by_cat.items(), key=lambda x: -x[1])},
        "render_parts_ms": dict(app.last_render_ms),
    }


def report(label: str, r: dict) -> None:
    client = f"; client got {r['client_kb']:.1f} KB" if r["client_kb"] is not None else ""
    print(
        f"{label}: median {r['median_ms']:.1f} ms, p95 {r['p95_ms']:.1f} ms "
        f"(CPU {r['median_cpu_ms']:.1f} / {r['p95_cpu_ms']:.1f} ms); "
        f"{r['median_kb']:.1f} KB per frame change (mean {r['mean_kb']:.1f}{client}), "
        f"of which meshes {r['meshes_kb']:.1f} KB"
    )
    for k, v in list(r["breakdown_kb"].items())[:8]:
        print(f"    {k:<40s} {v:8.1f} KB (uncompressed)")


def start_app(scene, results, model, frames, **options) -> tuple[ViewerApp, MessageTap]:
    """The viewer with every layer on; ``options`` override layer options (e.g.
    ``rays_selected_only=False``, ``frustum_image_width=320``) or, for
    ``panel_image_width``, the state."""
    state = ViewerState.create(scene, results, model)
    on = {f.name: True for f in dataclasses.fields(state.layers) if f.type in ("bool", bool)}
    on["rays_selected_only"] = True  # the app's default: the selected track's rays
    on["offset_filtered"] = False  # a display option, not a layer
    on["meshes_selected_only"] = False  # every body, as before that option
    if "panel_image_width" in options:
        state.panel_image_width = options.pop("panel_image_width")
    state.layers = dataclasses.replace(state.layers, **{**on, **options})
    app = ViewerApp(state, host="127.0.0.1", port=free_port(), frames=frames)
    assert app.wait_idle(60)
    render, cpu_ms = app._render_locked, []

    def timed_render() -> None:  # CPU time of the render and image threads: robust to a
        t0 = time.thread_time()  # busy machine
        try:
            render()
        finally:
            cpu_ms.append((time.thread_time() - t0) * 1e3 + app.last_image_cpu_ms)

    app._render_locked, app.bench_cpu_ms = timed_render, cpu_ms
    return app, MessageTap(app.server)


def meshes_on_off(run, repeats: int) -> dict:
    """Frame changes with the meshes on and off, alternated ``repeats`` times: medians over
    the runs' medians, and on / off."""
    off = {"meshes": False, "fit_meshes": False, "bodies_on_images": False}
    runs: dict[str, list[dict]] = {"on": [], "off": []}
    for i in range(repeats):
        runs["on"].append(run(f"meshes on, run {i + 1}/{repeats}"))
        runs["off"].append(run(f"meshes off, run {i + 1}/{repeats}", **off))
    out = {}
    for key in ("on", "off"):
        rs = runs[key]
        out[f"meshes_{key}"] = {
            k: float(np.median([r[k] for r in rs]))
            for k in ("median_ms", "p95_ms", "median_cpu_ms", "median_kb")
        }
    on, of = out["meshes_on"], out["meshes_off"]
    print(
        f"meshes on: {on['median_ms']:.1f} ms (CPU {on['median_cpu_ms']:.1f} ms), "
        f"{on['median_kb']:.1f} KB; off: {of['median_ms']:.1f} ms (CPU "
        f"{of['median_cpu_ms']:.1f} ms), {of['median_kb']:.1f} KB per frame change; on / off "
        f"{on['median_ms'] / of['median_ms']:.2f}x the time, "
        f"{on['median_kb'] / of['median_kb']:.2f}x the bytes (medians of {repeats} runs)"
    )
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--scene", type=Path, default=REPO / "sample_data" / "shelf_synth")
    ap.add_argument("--changes", type=int, default=100, help="random frame changes per mode")
    ap.add_argument("--client", action="store_true", help="also count bytes at a ws client")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=None, help="write the figures here")
    ap.add_argument("--docs", action="store_true", help="write the documentation's section")
    ap.add_argument(
        "--rerun-only", action="store_true", help="only the default with and without --rerun"
    )
    ap.add_argument(
        "--browser-playback", action="store_true",
        help="only 1x playback in headless chromium: the page's lag (tools/playback_probe.py)",
    )  # fmt: skip
    ap.add_argument("--seconds", type=float, default=15.0, help="--browser-playback's length")
    ap.add_argument(
        "--meshes-on-off", action="store_true",
        help="only the frame changes with the meshes on and off, alternated",
    )  # fmt: skip
    ap.add_argument("--repeats", type=int, default=3, help="--meshes-on-off's alternations")
    args = ap.parse_args(argv)

    scene = load_scene(args.scene)
    model = load_body_model()
    results, _ = run_or_load(scene, PipelineConfig(), model, progress=False)
    frames = FrameStore(scene, cache_dir=scene.root / CACHE_DIR / "frames").start()
    assert frames.wait(600), "decoding the videos took too long"
    rng = np.random.default_rng(args.seed)
    changes = rng.integers(0, scene.num_frames, args.changes)
    warm = rng.integers(0, scene.num_frames, 5)
    out: dict = {"scene": scene.name, "changes": int(args.changes)}
    if args.browser_playback:
        if not CHROMIUM.exists():
            raise SystemExit(f"{CHROMIUM} is absent (apt-get install chromium)")
        out["browser_playback"] = browser_playback(scene, results, model, frames, args.seconds)
        if args.json:
            write_json(args.json, out)
        return out

    def run(label: str, setup=None, core: bool = False, **options) -> dict:
        app, tap = start_app(scene, results, model, frames, **options)
        if core:  # the viewer alone: other panels' per-frame work (e.g. plots) detached
            for panel in app.panels:  # stopped panels no longer follow the frame
                panel.stop()
        client = WireClient(app.url) if args.client else None
        try:
            if client:
                time.sleep(2.0)  # the initial scene
            extra = setup(app) if setup else None
            measure(app, tap, warm, None)
            r = measure(app, tap, changes, client)
            if extra is not None:
                r["full_mesh_vertices"] = extra
            report(label, r)
            return r
        finally:
            if client:
                client.close()
            app.stop()

    load = os.getloadavg()[0] / (os.cpu_count() or 1)
    print(
        f"{scene.name}: {len(scene.rig)} cameras, {scene.num_frames} frames, every layer on "
        f"(videos on the frustums and in the camera panel, 2D joints, the selected track's "
        f"rays, raw / filtered / ground-truth skeletons, trails, ground-truth and fitted "
        f"skinned meshes) and every panel attached; load {load:.1f} per CPU (wall-clock "
        f"times grow with it; CPU times much less)"
    )
    out["load_per_cpu"] = load
    if args.meshes_on_off:
        out.update(meshes_on_off(run, args.repeats))
        if args.json:
            write_json(args.json, out)
        return out
    skinned = out["skinned"] = run("skinned meshes (bone poses)")
    out["rerun"] = rerun_overhead(lambda: start_app(scene, results, model, frames), changes, warm)
    if args.rerun_only:
        if args.json:
            write_json(args.json, out)
        return out
    full = out["full"] = run("full vertex arrays", use_full_vertex_meshes)
    ratio_kb = full["median_kb"] / skinned["median_kb"]
    ratio_mesh = full["meshes_kb"] / max(skinned["meshes_kb"], 1e-9)
    ratio_ms = full["median_ms"] / skinned["median_ms"]
    out.update(ratio_bytes=ratio_kb, ratio_mesh_bytes=ratio_mesh, ratio_time=ratio_ms)
    print(
        f"full vertices / skinned: {ratio_kb:.1f}x the bytes per frame change "
        f"({ratio_mesh:.0f}x for the meshes alone), {ratio_ms:.1f}x the time"
    )

    ok_ms, ok_kb = skinned["median_ms"] <= TARGET_MS, skinned["median_kb"] <= TARGET_KB
    print(
        f"targets (skinned): median {skinned['median_ms']:.1f} ms "
        f"(CPU {skinned['median_cpu_ms']:.1f} ms) <= {TARGET_MS:.0f} ms "
        f"{'met' if ok_ms else 'MISSED'}; {skinned['median_kb']:.1f} KB <= {TARGET_KB:.0f} KB "
        f"{'met' if ok_kb else 'MISSED'}"
    )
    out["targets_met"] = {"time": bool(ok_ms), "bytes": bool(ok_kb)}
    if not (ok_ms and ok_kb):
        top = next(iter(skinned["breakdown_kb"].items()))
        parts = skinned["render_parts_ms"]
        print(
            f"dominating: bytes {top[0]} ({top[1]:.1f} KB); time "
            + ", ".join(f"{k} {v:.1f} ms" for k, v in parts.items())
        )
    # What the options and the design choices cost, in the same run:
    variants = out["variants"] = {}
    for key, label, setup, kw in (
        ("all_rays", "every track's rays (the 'selected track only' option off)", None,
         {"rays_selected_only": False}),
        ("sharp_images", "sharp videos: 320 px frustums, 640 px camera panel", None,
         {"frustum_image_width": 320, "panel_image_width": 640}),
        ("public_bone_setters", "bones posed through viser's per-bone setters",
         use_public_bone_setters, {}),
        ("viewer_alone", "viewer alone (other panels' per-frame callbacks detached)", None,
         {"core": True}),
    ):  # fmt: skip
        r = variants[key] = run(label, setup, **kw)
        print(
            f"    -> {r['median_ms'] / skinned['median_ms']:.2f}x the time, "
            f"{r['median_kb'] / skinned['median_kb']:.2f}x the bytes of the default"
        )
    if args.json:
        write_json(args.json, out)
    if args.docs:
        rows = [["default: skinned meshes", f"{skinned['median_ms']:.1f}",
                 f"{skinned['p95_ms']:.1f}", f"{skinned['median_kb']:.1f}", "1.00x / 1.00x"],
                ["full vertex arrays instead", f"{full['median_ms']:.1f}", f"{full['p95_ms']:.1f}",
                 f"{full['median_kb']:.1f}", f"{ratio_ms:.2f}x / {ratio_kb:.1f}x"]]  # fmt: skip
        for key, r in variants.items():
            rows.append([key.replace("_", " "), f"{r['median_ms']:.1f}", f"{r['p95_ms']:.1f}",
                         f"{r['median_kb']:.1f}",
                         f"{r['median_ms'] / skinned['median_ms']:.2f}x / "
                         f"{r['median_kb'] / skinned['median_kb']:.2f}x"])  # fmt: skip
        publish("bench_viewer", "Viewer frame changes", (
            f"{args.changes} random frame changes of the viewer on `{args.scene.name}`, every "
            f"layer and panel on; server-side time and bytes sent per change (targets "
            f"{TARGET_MS:.0f} ms and {TARGET_KB:.0f} KB).\n\n"
            + markdown_table(["variant", "median ms", "p95 ms", "KB per change",
                              "time / bytes vs default"], rows)))  # fmt: skip
    return out


if __name__ == "__main__":
    main()
