"""Headless Debian chromium for tests, benchmarks and README screenshots.

viser's WebGL renders in headless chromium through SwiftShader with
``--enable-unsafe-swiftshader --use-angle=swiftshader`` (``--use-gl=swiftshader`` breaks
it). Playwright drives ``/usr/bin/chromium`` (Debian package ``chromium``); never
``playwright install``, which downloads a browser.
"""

from __future__ import annotations

from pathlib import Path

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader",
    "--no-sandbox",
    "--disable-gpu-sandbox",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


def pinned_dpr_url(url: str, dpr: float = 1.0) -> str:
    """``url`` with viser's ``fixedDpr`` query: the page renders at ``dpr`` always.

    viser's client lowers its device-pixel ratio (to 0.75 here) once it has drawn ~10
    consecutive 250 ms windows slowly, which software WebGL does during playback or a
    run of frame changes, and raises it only after as many fast windows: lines come out
    thinner and paler, point sprites smaller. A picture then depends on what the page
    drew before, not on what it shows, so pictures that are compared pin the ratio.
    """
    sep = "&" if "?" in url else "?"
    return f"{url}{sep}fixedDpr={dpr:g}"


def launch_chromium(playwright):
    """A headless chromium browser from a ``sync_playwright()`` context."""
    return playwright.chromium.launch(
        executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS
    )


def close_webgl_notice(page, timeout_ms: int = 5_000) -> None:
    """Close viser's "software WebGL" notification if it shows up."""
    close = page.locator("button.mantine-Notification-closeButton")
    try:
        close.first.wait_for(timeout=timeout_ms)
        close.first.click()
    except Exception:
        pass  # no notice (hardware WebGL) or it already went
