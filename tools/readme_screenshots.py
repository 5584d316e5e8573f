"""Take the README's viewer screenshots: the debugger on a scene, in headless Chromium.

Starts the viewer on SCENE (cached results), opens it in Debian's chromium (software
WebGL), sets a frame, selection and layers, and writes a PNG.

Usage:
    python tools/readme_screenshots.py SCENE OUT.png [--frame F] [--track K]
        [--fit-meshes] [--no-rays] [--camera NAME] [--tab NAME] [--criterion C] [--port P]

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


def main() -> None:
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
