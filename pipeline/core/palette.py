"""One colour per track id, for every drawing of a run: the viewer
(:data:`mvviz.scene.geometry.PALETTE`), the rerun recording
(:func:`mvviz.export.rerun.layout.track_color`) and the file exports
(:mod:`pipeline.exports`) colour track ``k`` alike.

Colours are sRGB 0-255 (matplotlib's tab10 without red, which the viewer keeps for
outliers, and grey, which means "unassigned").
"""

from __future__ import annotations

TRACK_PALETTE: tuple[tuple[int, int, int], ...] = (
    (31, 119, 180),  # blue
    (255, 127, 14),  # orange
    (44, 160, 44),  # green
    (148, 103, 189),  # purple
    (23, 190, 207),  # cyan
    (227, 119, 194),  # pink
    (188, 189, 34),  # olive
    (140, 86, 75),  # brown
)


def track_rgb(track: int) -> tuple[int, int, int]:
    """The colour of track id ``track`` (sRGB 0-255), cycling through :data:`TRACK_PALETTE`."""
    return TRACK_PALETTE[int(track) % len(TRACK_PALETTE)]
