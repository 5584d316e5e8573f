"""Take the README's viewer screenshots: the debugger on a scene, in headless Chromium.

Starts the viewer on SCENE (cached results), opens it in Debian's chromium (software
WebGL), sets a frame, selection and layers, and writes a PNG.

Usage:
    python tools/readme_screenshots.py SCENE OUT.png [--frame F] [--track K]
        [--fit-meshes] [--no-rays] [--camera NAME] [--tab NAME] [--criterion C] [--port P]
    python tools/readme_screenshots.py --all [--capture SCENE]

--all regenerates every screenshot of the README and the documentation
(docs/screenshots/, the table ``SHOTS``); --capture is the tutorial's scene (made by the
tutorial's commands), whose picture is skipped without it.

--tab shows a tab of the right-hand panel ("Failures", ...); --criterion sets the
Failures panel's criterion ("association", ...) before the picture.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mvviz.cli.view import add_view_options, start  # noqa: E402
from tools.chromium import close_webgl_notice, launch_chromium, pinned_dpr_url  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SHOTS = {  # docs/screenshots/<name>.png: the scene and this tool's options
    "viewer": ("sample_data/shelf_synth", ["--frame", "60", "--track", "0"]),
    "pose2sim_demo": ("sample_data/pose2sim_demo", ["--frame", "40", "--track", "0"]),
    "filter_ab": ("sample_data/shelf_synth", ["--frame", "120", "--tab", "Filter A/B"]),
    "failures": ("sample_data/shelf_synth_noisy", ["--frame", "60", "--tab", "Failures"]),
    "pose2sim_balancing": ("sample_data/pose2sim_balancing", ["--frame", "50"]),
    "pose2sim_balancing_meshes": ("sample_data/pose2sim_balancing",
                                  ["--frame", "50", "--fit-meshes", "--no-rays"]),
    "tutorial_capture": (None, ["--frame", "20", "--track", "0"]),
}  # fmt: skip


def regenerate_all(capture: Path | None) -> int:
    """Every picture of ``SHOTS``, each by a run of this tool in its own process."""
    import subprocess

    failed = []
    for name, (scene, options) in SHOTS.items():
        if scene is None and capture is None:
            print(f"skipped {name}: needs --capture SCENE (the tutorial's scene)")
            continue
        out = REPO / "docs" / "screenshots" / f"{name}.png"
        argv = [sys.executable, __file__, str(capture if scene is None else REPO / scene),
                str(out), *options]  # fmt: skip
        if subprocess.run(argv, cwd=REPO).returncode != 0:
            failed.append(name)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


def main() -> None:
    if "--all" in sys.argv[1:]:
        capture = None
        if "--capture" in sys.argv:
            capture = Path(sys.argv[sys.argv.index("--capture") + 1]).resolve()
        raise SystemExit(regenerate_all(capture))
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_view_options(ap)
    # not "out": the view options' --out is the results path (a directory unless .npz)
    ap.add_argument("png", type=Path)
    ap.set_defaults(frame=60, track=0)  # the view options' --frame / --track, other defaults
    ap.add_argument("--fit-meshes", action="store_true")
    ap.add_argument("--no-rays", action="store_true")
    ap.add_argument("--camera", default=None)
    ap.add_argument("--tab", default=None, help='a tab of the right-hand panel, e.g. "Failures"')
    ap.add_argument("--criterion", default=None, help="the Failures panel's criterion")
    args = ap.parse_args()
    app = start(args, progress=False)
    if app.frames is not None:
        deadline = time.time() + 120
        while not app.frames.ready and time.time() < deadline:
            time.sleep(0.5)
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = launch_chromium(pw)
        page = browser.new_page(viewport={"width": 1600, "height": 900})
        page.goto(pinned_dpr_url(app.url))  # crisp pictures whatever the page drew before
        page.wait_for_selector("canvas", timeout=60_000)
        close_webgl_notice(page)
        page.wait_for_timeout(3000)
        lp = app.layers_panel.gui.toggles
        lp["fit_meshes"].value = args.fit_meshes
        lp["rays"].value = not args.no_rays
        if args.criterion:
            app.failure_panel.set_criterion(args.criterion)
        app.jump_to(frame=args.frame, track=args.track, view=args.camera)
        app.wait_idle(30)
        if args.tab:
            page.get_by_role("tab", name=args.tab).click()
        page.wait_for_timeout(6000)
        page.screenshot(path=str(args.png))
        browser.close()
    app.stop()
    print(f"wrote {args.png}")


if __name__ == "__main__":
    main()
