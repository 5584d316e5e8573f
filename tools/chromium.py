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
