"""viser's button and tab icons read from one open zip file.

viser reads each icon with ``zipfile.ZipFile(tabler-icons.zip)``, which parses the
archive's whole central directory (~4,300 entries) for every new icon: the viewer's 16
icons cost 1-1.5 s of its start on a busy machine (measured with cProfile in
bench/bench_viewer_scale.py's scene). :func:`use_one_icon_zip` opens the archive once and
serves every icon from it; the icons are the same bytes.
"""

from __future__ import annotations

import functools
import threading
import zipfile

_lock = threading.Lock()
_installed = False


def use_one_icon_zip() -> None:
    """Replace viser's ``svg_from_icon`` (in the modules that call it) by one reading
    from a single open :class:`zipfile.ZipFile`. Idempotent; a viser without those
    modules is left as it is."""
    global _installed
    with _lock:
        if _installed:
            return
        try:
            from viser import _gui_api, _gui_handles, _icons
        except ImportError:
            return
        if not all(hasattr(m, "svg_from_icon") for m in (_gui_api, _gui_handles, _icons)):
            return
        archive = zipfile.ZipFile(_icons.ICONS_DIR / "tabler-icons.zip")
        archive_lock = threading.Lock()

        @functools.cache
        def svg_from_icon(icon_name: str) -> str:
            assert isinstance(icon_name, str)
            with archive_lock, archive.open(f"{icon_name}.svg") as fh:
                return fh.read().decode("utf-8")

        for module in (_gui_api, _gui_handles, _icons):
            module.svg_from_icon = svg_from_icon
        _installed = True
