"""Benchmark the time from ``python app.py`` to a usable page, with a warm cache.

Starts ``python app.py SCENE --port P`` as a user would (cached pipeline results and
decoded videos from an earlier start; one uncounted warm-up start makes sure), and
measures from the command:

- to the first HTTP answer on the port (polled every 20 ms): a browser gets a page;
- to the URL line ("ready in ... s: http://..."): the server is up with the scene;
- with Debian's chromium (playwright): to a page showing the scene, i.e. the viewer
  has loaded, the frame label has arrived and the 3D canvas is not blank.

Baselines measured in the same run: ``python -c "import mvviz.app"``, the viewer's
imports alone (torch, viser, scipy, matplotlib), which ``mvviz view`` pays after its
server answers and before the scene is shown; and a bare viser
server showing a grid and a box, opened the same way, the floor of the browser side (loading
viser's client and software-rendering WebGL in headless chromium). Prints medians of
--runs starts and the differences to the floors.

With --compare-with DIR (another checkout of the project, e.g. ``git worktree add
/tmp/before REV``), every start of this checkout's ``app.py`` is followed by one of
DIR's (its own package first on PYTHONPATH, its own cache under DIR/sample_data), in the
same browser: medians of both and the ratios, measured under the same load.

--via-cli starts ``mvviz view`` (as ``python -m mvviz.cli view``) instead of app.py.

Usage:
    python bench/bench_startup.py [--scene DIR] [--runs N] [--json FILE] [--compare-with DIR]
                                  [--via-cli]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.common import free_port, write_json  # noqa: E402
from tools.chromium import CHROMIUM, close_webgl_notice, launch_chromium  # noqa: E402

START_COMMAND = [sys.executable, "app.py"]  # --via-cli: python -m mvviz.cli view


def repo_env(repo: Path) -> dict[str, str]:
    """The environment that makes ``repo``'s own package the one imported."""
    return {**os.environ, "PYTHONPATH": str(repo)}


def time_imports(repo: Path = REPO) -> float:
    t0 = time.perf_counter()
    subprocess.run(
        [sys.executable, "-c", "import mvviz.app"], check=True, cwd=repo, env=repo_env(repo)
    )
    return time.perf_counter() - t0


def canvas_std(page) -> float:
    png = page.locator("canvas").first.screenshot()
    return float(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).std())


BARE_VISER = """
import sys, time, viser
server = viser.ViserServer(host="127.0.0.1", port=int(sys.argv[1]))
server.scene.add_grid("/grid", width=6.0, height=6.0)
server.scene.add_box("/box", color=(200, 40, 40), dimensions=(1.5, 1.5, 1.5))
server.gui.add_markdown("frame 0 / 1")
print("ready in 0 s", flush=True)
time.sleep(600)
"""


def poll_http(url: str, t0: float, out: dict[str, float], stop: threading.Event) -> None:
    """Set ``out["http_s"]`` to the seconds since ``t0`` of the first answer from ``url``."""
    while not stop.is_set():
        try:
            with urllib.request.urlopen(url, timeout=1.0) as r:
                r.read(1)
            out["http_s"] = time.perf_counter() - t0
            return
        except OSError:
            time.sleep(0.02)


def time_start(scene: Path | None, browser, repo: Path = REPO) -> dict[str, float]:
    """Seconds from the command to the first HTTP answer, the URL line and (with
    ``browser``) a drawn page. ``scene`` None: the bare viser server instead of the app;
    ``repo``: the checkout whose app.py runs."""
    port = free_port()
    out: dict[str, float] = {}
    stop = threading.Event()
    t0 = time.perf_counter()
    poller = threading.Thread(
        target=poll_http, args=(f"http://127.0.0.1:{port}", t0, out, stop), daemon=True
    )
    poller.start()
    cmd = [*START_COMMAND, str(scene), "--port", str(port)]
    if scene is None:
        cmd = [sys.executable, "-c", BARE_VISER, str(port)]
    proc = subprocess.Popen(
        cmd, cwd=repo, env=repo_env(repo), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        text=True,
    )  # fmt: skip
    try:
        for line in proc.stdout:
            if line.startswith("ready in"):
                out["url_s"] = time.perf_counter() - t0
                break
        else:
            raise RuntimeError(f"app.py exited with {proc.wait()} before it was ready")
        if browser is not None:
            page = browser.new_page(viewport={"width": 1400, "height": 860})
            page.goto(f"http://127.0.0.1:{port}")
            page.wait_for_selector("canvas", timeout=60_000)
            page.wait_for_function(
                "() => /frame \\d+ \\/ \\d+/.test(document.body.innerText)", timeout=60_000
            )
            close_webgl_notice(page, timeout_ms=500)
            deadline = time.perf_counter() + 60
            while canvas_std(page) < 15 and time.perf_counter() < deadline:
                time.sleep(0.1)
            out["page_s"] = time.perf_counter() - t0
            page.close()
    finally:
        poller.join(timeout=10)
        stop.set()
        proc.terminate()
        proc.wait(timeout=30)
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--scene", type=Path, default=REPO / "sample_data" / "shelf_synth")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument(
        "--compare-with", type=Path, default=None, metavar="DIR",
        help="another checkout: its app.py started after each of this one's",
    )  # fmt: skip
    ap.add_argument(
        "--via-cli", action="store_true",
        help="start `python -m mvviz.cli view SCENE` (mvviz view) instead of app.py",
    )  # fmt: skip
    args = ap.parse_args(argv)
    if args.via_cli:
        START_COMMAND[1:] = ["-m", "mvviz.cli", "view"]
    if args.compare_with is not None:
        return compare(args)

    load = os.getloadavg()[0] / (os.cpu_count() or 1)
    print(f"{args.scene.name}: {args.runs} starts after a warm-up; load {load:.1f} per CPU")
    pw_ctx = browser = None
    if CHROMIUM.exists():
        from playwright.sync_api import sync_playwright  # dev extra

        pw_ctx = sync_playwright().start()
        browser = launch_chromium(pw_ctx)
    else:
        print(f"({CHROMIUM} absent: only the time to the URL line is measured)")
    try:
        time_start(args.scene, None)  # warm-up: caches, OS file cache
        imports = [time_imports() for _ in range(args.runs)]
        starts = [time_start(args.scene, browser) for _ in range(args.runs)]
        bare = [time_start(None, browser) for _ in range(args.runs)] if browser else []
    finally:
        if browser is not None:
            browser.close()
            pw_ctx.stop()
    out = {"scene": args.scene.name, "runs": args.runs, "load_per_cpu": load}
    out["imports_s"] = statistics.median(imports)
    print(f"the viewer's imports alone (python -c 'import mvviz.app'): {out['imports_s']:.2f} s")
    for key, label in (
        ("http_s", "to the first HTTP answer"),
        ("url_s", "to the URL line"),
        ("page_s", "to a drawn page"),
    ):
        values = [s[key] for s in starts if key in s]
        if values:
            out[key] = statistics.median(values)
            print(
                f"python app.py {label}: median {out[key]:.2f} s "
                f"(runs: {', '.join(f'{v:.2f}' for v in values)}); "
                f"{out[key] / out['imports_s']:.1f}x the imports"
            )
    if bare and "page_s" in out:
        out["bare_viser_page_s"] = statistics.median(b["page_s"] for b in bare)
        out["bare_viser_url_s"] = statistics.median(b["url_s"] for b in bare)
        print(
            f"bare viser server (grid and box): URL {out['bare_viser_url_s']:.2f} s, drawn page "
            f"{out['bare_viser_page_s']:.2f} s; the browser side of python app.py takes "
            f"{out['page_s'] - out['url_s']:.2f} s vs "
            f"{out['bare_viser_page_s'] - out['bare_viser_url_s']:.2f} s for the bare server"
        )
    if args.json:
        write_json(args.json, out)
    return out


def compare(args: argparse.Namespace) -> dict:
    """This checkout's starts alternated with ``args.compare_with``'s, same browser."""
    other = args.compare_with.resolve()
    scene_rel = args.scene.resolve().relative_to(REPO)
    repos = {"this": (REPO, REPO / scene_rel), "other": (other, other / scene_rel)}
    load = os.getloadavg()[0] / (os.cpu_count() or 1)
    print(f"{scene_rel}: {args.runs} alternated starts of {REPO} and {other}; load {load:.1f}")
    pw_ctx = browser = None
    if CHROMIUM.exists():
        from playwright.sync_api import sync_playwright  # dev extra

        pw_ctx = sync_playwright().start()
        browser = launch_chromium(pw_ctx)
    starts: dict[str, list[dict[str, float]]] = {k: [] for k in [*repos, "bare"]}
    imports: dict[str, list[float]] = {k: [] for k in repos}
    try:
        for repo, scene in repos.values():
            time_start(scene, None, repo)  # warm-up: each checkout's caches, OS file cache
        for _ in range(args.runs):
            for key, (repo, scene) in repos.items():
                imports[key].append(time_imports(repo))
                starts[key].append(time_start(scene, browser, repo))
            if browser is not None:  # the floor: a bare viser server, same browser and load
                starts["bare"].append(time_start(None, browser))
    finally:
        if browser is not None:
            browser.close()
            pw_ctx.stop()
    out: dict = {"scene": str(scene_rel), "runs": args.runs, "load_per_cpu": load,
                 "this": str(REPO), "other": str(other)}  # fmt: skip
    for key in [*repos, "bare"]:
        if imports.get(key):
            out[key + "_imports_s"] = statistics.median(imports[key])
            out[key + "_imports_s_runs"] = imports[key]
        for m in ("http_s", "url_s", "page_s"):
            values = [s[m] for s in starts[key] if m in s]
            if values:
                out[f"{key}_{m}"] = statistics.median(values)
                out[f"{key}_{m}_runs"] = values
    for m, label in (("imports_s", "import mvviz.app"), ("http_s", "first HTTP answer"),
                     ("url_s", "URL line (scene ready)"), ("page_s", "drawn page")):  # fmt: skip
        if f"this_{m}" in out and f"other_{m}" in out:
            a, b = out[f"this_{m}"], out[f"other_{m}"]
            runs = {k: ", ".join(f"{v:.2f}" for v in out.get(f"{k}_{m}_runs", [])) for k in repos}
            print(f"{label}: this {a:.2f} s ({runs['this']}), other {b:.2f} s "
                  f"({runs['other']}); this / other {a / b:.2f}")  # fmt: skip
    if "bare_page_s" in out:
        bare_runs = ", ".join(f"{v:.2f}" for v in out["bare_page_s_runs"])
        bare_side = out["bare_page_s"] - out["bare_url_s"]
        print(
            f"bare viser server (grid and box): URL {out['bare_url_s']:.2f} s, drawn page "
            f"{out['bare_page_s']:.2f} s ({bare_runs})"
        )
        for key in repos:
            if f"{key}_page_s" in out:
                side = out[f"{key}_page_s"] - out[f"{key}_url_s"]
                print(f"{key}: the browser side takes {side:.2f} s vs {bare_side:.2f} s bare")
    out["load_per_cpu_after"] = os.getloadavg()[0] / (os.cpu_count() or 1)
    print(f"load after: {out['load_per_cpu_after']:.1f} per CPU")
    if args.json:
        write_json(args.json, out)
    return out


if __name__ == "__main__":
    main()
