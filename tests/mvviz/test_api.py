"""The Python API a notebook uses: the same results as the command line's cache, settings
by overrides, and the viewer served in the background, shown in the cell under Jupyter."""

from __future__ import annotations

import sys
import types
import urllib.request

import numpy as np
import pytest

import mvviz
from tests.mvviz.conftest import free_port


def test_run_reuses_the_cache_and_takes_overrides(viewer_scene):
    scene, results, _ = viewer_scene
    again = mvviz.run(scene.root, progress=False)  # a path, as a notebook passes it
    assert again.cache_key == results.cache_key
    np.testing.assert_array_equal(again.track_filtered, results.track_filtered)
    cache = scene.root / ".mvviz"
    before = sorted(p.name for p in cache.rglob("*"))
    raw_only = mvviz.run(scene, overrides=["fit_smpl=false"], cache=False, progress=False)
    assert raw_only.smpl is None and results.smpl is not None
    assert sorted(p.name for p in cache.rglob("*")) == before  # cache=False wrote nothing
    scores = mvviz.evaluate(scene, raw_only)
    assert scores.stages["rts"]["mpjpe"] < scores.stages["raw"]["mpjpe"] < 40.0


def test_a_bad_override_is_one_clear_error(viewer_scene):
    scene, _, _ = viewer_scene
    with pytest.raises(Exception, match="kalman") as info:
        mvviz.config_of(scene, overrides=["kalman.q=fast"])
    assert type(info.value).__name__ == "SceneFormatError"


def test_show_serves_the_viewer_inline_in_jupyter(viewer_scene, monkeypatch):
    """Under a Jupyter kernel the page is displayed in the cell (an IFrame of its URL)."""
    scene, results, _ = viewer_scene
    shown = []
    ipython = types.ModuleType("IPython")
    ipython.get_ipython = lambda: types.SimpleNamespace(config={"IPKernelApp": {}})
    display = types.ModuleType("IPython.display")
    display.IFrame = lambda src, width, height: ("iframe", src, width, height)
    display.display = shown.append
    ipython.display = display
    monkeypatch.setitem(sys.modules, "IPython", ipython)
    monkeypatch.setitem(sys.modules, "IPython.display", display)
    assert mvviz.api.in_notebook()
    viewer = mvviz.show(scene, results, port=free_port(), frame=5, track=1)
    try:
        assert shown == [("iframe", viewer.url, "100%", 640)]
        with urllib.request.urlopen(viewer.url, timeout=30) as answer:
            assert answer.status == 200
        assert viewer.state.frame == 5
    finally:
        viewer.stop()
    with pytest.raises(Exception, match="expected 0..1"):
        mvviz.show(scene, results, port=free_port(), track=7, inline=False)


def test_import_mvviz_loads_no_pipeline():
    """``import mvviz`` is instant: the API's modules load when a function is called."""
    import subprocess

    probe = "import sys, mvviz; print(any(m.startswith(('pipeline', 'torch', 'viser')) " \
            "for m in sys.modules))"  # fmt: skip
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         check=True)  # fmt: skip
    assert out.stdout.strip() == "False"
