"""How far the page trails the server during playback, as a person would see it.

The server side records every frame the app renders (in order) and, for every
camera-panel picture it sends, the SHA-1 of the JPEG bytes and the frame it shows. The
page is sampled every ``interval_s``; a sample reads at one moment the frame label it
shows ("frame N / M", which arrives in the same message batch as the 3D scene updates of
that frame, so it stands for the 3D view) and the blob URL of every picture it shows,
then hashes the pictures (cached per URL), which names the frame of the camera picture
on screen. Per sample:

- ``image_lag``: label frame minus camera-picture frame (the picture trailing the 3D
  view), in frames of the video;
- ``sent_lag``: frames the server had rendered and sent that the page did not show yet
  (0: it shows the newest). The server's count is read just before and just after the
  sample; ``sent_lag`` uses the later one, an upper bound (``sent_lag_low`` the lower);
- ``label_lag``: the server's frame just before the sample minus the label frame, in
  frames of the video (large when frames are dropped: that is not lag).

Used by ``bench/bench_viewer.py --browser-playback`` and the browser test of playback.
"""

from __future__ import annotations

import hashlib
import threading
import time
from dataclasses import dataclass

import numpy as np

# The label's frame and the pictures' URLs read at once, then their SHA-1s (hex).
SAMPLE_JS = """
async () => {
  const m = document.body.textContent.match(/frame (\\d+) \\/ (\\d+) /);
  const srcs = Array.from(document.querySelectorAll('img'))
      .filter(i => i.src.startsWith('blob:') && i.complete && i.naturalWidth > 0)
      .map(i => i.src);
  const cache = window.__mvvizProbe || (window.__mvvizProbe = new Map());
  const hashes = [];
  for (const src of srcs) {
    if (!cache.has(src)) {
      try {
        const buf = await (await fetch(src)).arrayBuffer();
        const d = new Uint8Array(await crypto.subtle.digest('SHA-1', buf));
        cache.set(src, Array.from(d, b => b.toString(16).padStart(2, '0')).join(''));
      } catch (e) { continue; }  // revoked while we read it
    }
    hashes.push(cache.get(src));
  }
  return {label: m ? parseInt(m[1]) : null, hashes};
}
"""


class PictureLog:
    """The frames the app renders, in order, and the SHA-1 of each camera-panel JPEG
    it sends -> the frame it shows."""

    def __init__(self, app) -> None:
        self.frame_of: dict[str, int] = {}
        self.rendered: list[int] = []  # every frame rendered, in order
        self._lock = threading.Lock()
        panel, timeline = app.camera_panel, app.timeline
        show_image, show_frame = panel.show_image, timeline.show_frame

        def frame_hook(state) -> None:  # the render shows the frame, then the picture
            with self._lock:
                self.rendered.append(state.frame)
            show_frame(state)

        def image_hook(image) -> None:
            show_image(image)
            data = bytes(panel.gui.image._data)  # the bytes viser sends (encoded once)
            with self._lock:
                self.frame_of[hashlib.sha1(data).hexdigest()] = self.rendered[-1]

        timeline.show_frame, panel.show_image = frame_hook, image_hook

    def frame(self, hashes: list[str]) -> int | None:
        with self._lock:
            found = [self.frame_of[h] for h in hashes if h in self.frame_of]
        return found[0] if found else None

    def count(self) -> int:
        with self._lock:
            return len(self.rendered)

    def behind(self, frame: int, count: int) -> int | None:
        """Renders among the first ``count`` after the last one of ``frame``."""
        with self._lock:
            seen = self.rendered[:count]
        for i in range(len(seen) - 1, max(len(seen) - 500, -1), -1):
            if seen[i] == frame:
                return len(seen) - 1 - i
        return None


@dataclass(frozen=True)
class PlaybackLag:
    samples: int  # samples with both a label and a camera picture
    image_lag: np.ndarray  # (samples,) video frames the picture trails the label
    sent_lag: np.ndarray  # (samples,) rendered frames not yet shown (upper bound)
    sent_lag_low: np.ndarray  # (samples,) the same, lower bound
    label_lag: np.ndarray  # (samples,) video frames the label trails the server
    frames_advanced: int  # server frames played during the sampling
    renders: int  # frames rendered (sent) during the sampling
    seconds: float

    def summary(self) -> str:
        def s(x: np.ndarray) -> str:
            return f"median {np.median(x):.1f}, max {x.max():.0f}" if x.size else "no samples"

        return (
            f"{self.samples} samples over {self.seconds:.1f} s ({self.frames_advanced} frames "
            f"played, {self.renders} sent): camera picture behind the 3D view "
            f"{s(self.image_lag)} frames; the page behind the newest frame sent "
            f"{s(self.sent_lag)} (lower bound {s(self.sent_lag_low)}); frame label behind "
            f"the server's frame {s(self.label_lag)}"
        )


def measure_playback(
    app, page, log: PictureLog, *, seconds: float = 8.0, interval_s: float = 0.1,
    speed: float = 1.0, min_samples: int = 0, max_seconds: float | None = None,
) -> PlaybackLag:  # fmt: skip
    """Play at ``speed`` for ``seconds`` and sample the page; stops playing after. With
    ``min_samples``, goes on past ``seconds`` (up to ``max_seconds``) until that many
    samples are taken: on a busy machine a software-WebGL page can stand still for
    seconds, and a figure needs samples."""
    n = app.state.data.num_frames
    app.state.speed, app.state.loop, app.state.playing = speed, True, True
    app.redraw("playing")
    image_lag, sent_hi, sent_lo, label_lag = [], [], [], []
    time.sleep(1.0)  # the first frames of playback
    t0, r0, played0 = time.perf_counter(), log.count(), app.frames_played
    limit = seconds if max_seconds is None else max(seconds, max_seconds)
    while (elapsed := time.perf_counter() - t0) < seconds or (
        len(image_lag) < min_samples and elapsed < limit
    ):
        server_frame, before = app.state.frame, log.count()
        got = page.evaluate(SAMPLE_JS)
        after = log.count()
        picture, label = log.frame(got["hashes"]), got["label"]
        hi = None if label is None else log.behind(label, after)
        lo = None if label is None else log.behind(label, before)
        if picture is not None and hi is not None:
            image_lag.append((label - picture) % n)
            sent_hi.append(hi)
            sent_lo.append(lo if lo is not None else 0)
            label_lag.append((server_frame - label) % n)
        time.sleep(interval_s)
    took, renders = time.perf_counter() - t0, log.count() - r0
    advanced = app.frames_played - played0  # the player's own count: loops included
    app.state.playing = False
    app.redraw("playing")

    # (a - b) % n reads a frame one ahead (across the loop) as n - 1 behind
    def signed(x: list[int]) -> np.ndarray:
        return np.array([v if v < n // 2 else v - n for v in x], int)

    return PlaybackLag(
        len(image_lag), signed(image_lag), np.array(sent_hi, int), np.array(sent_lo, int),
        signed(label_lag), advanced, renders, took,
    )  # fmt: skip
