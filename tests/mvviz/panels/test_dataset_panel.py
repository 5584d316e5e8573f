"""The Dataset panel on a fake host, and ``python app.py --batch DIR`` in headless
chromium: scenes sorted by a metric, a click opens another scene at its worst moment."""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import pytest

from mvviz.cli.view_batch import first_row, scene_args, start_batch
from mvviz.panels.dataset_panel import make_dataset_panel, sort_rows
from pipeline.batch.jobs import summarize
from pipeline.batch.report import build_report, write_report
from pipeline.body.model import load_body_model
from pipeline.config import PipelineConfig
from pipeline.data.scene import load_scene
from pipeline.results.store import cache_key, save_results
from pipeline.run.pipeline import run_pipeline
from pipeline.synth.scene_gen import SynthConfig, write_synth_scene
from tests.mvviz.conftest import free_port
from tests.mvviz.panels.test_contract import FakeHost
from tests.pipeline.helpers import campus_rig
from tools.chromium import CHROMIUM, close_webgl_notice, launch_chromium


def row(label, mpjpe, pck, *, worst=((3, 1),), failed=False):
    summary = None
    moments = [{"frame": f, "track": t, "metric": "mpjpe_mm", "value": 99.0} for f, t in worst]
    if not failed:
        summary = {
            "mpjpe_mm": mpjpe, "pck160": pck, "reprojection_mean_px": 2.0,
            "worst": moments,
        }  # fmt: skip
    return {
        "scene": f"/data/{label}", "label": label, "setting": [], "set_args": [],
        "config_file": None, "status": "failed" if failed else "computed",
        "error": "ValueError: broken" if failed else None,
        "results": f"/data/{label}/.mvviz/results.npz", "summary": summary, "seconds": 1.0,
    }  # fmt: skip


@pytest.fixture
def host():
    h = FakeHost(SimpleNamespace(frame=0, snapshot=lambda: None))
    yield h
    h.stop()


def test_sorted_worst_first_and_a_click_opens(host):
    rows = [
        row("a", 30.0, 0.90, worst=((7, 2), (1, 0))),
        row("b", 50.0, 0.95),
        row("c", 0, 0, failed=True),
    ]
    report = build_report(rows)
    opened = []
    panel = make_dataset_panel(
        host, report, current=rows[0]["results"], open_scene=lambda r, m: opened.append((r, m))
    )
    assert panel.metric == "mpjpe_mm"  # the report's worst-scene metric
    assert [r["label"] for r in panel.rows] == ["b", "a", "c"]
    texts = [b.label for b in panel.gui.buttons]
    assert texts == ["b · 50.0", "▶ a · 30.0", "c · failed"]
    assert [b.disabled for b in panel.gui.buttons] == [False, False, True]
    assert panel.sort("pck160") == ["a", "b", "c"]  # lowest PCK first
    assert "PCK@160" in panel.gui.summary.content
    # the shown scene: a jump to its worst moment through the host
    assert panel.open("a") == {"frame": 7, "track": 2, "metric": "mpjpe_mm", "value": 99.0}
    assert host.asked("jump_to")[-1] == (7, 2, None, None) and not opened
    # another scene: handed to the command line's loader with its worst moment
    panel.open("b")
    assert opened[0][0]["label"] == "b" and opened[0][1]["frame"] == 3
    assert len(host.asked("jump_to")) == 1


def test_sort_rows_keeps_missing_figures_last():
    rows = [
        row("x", None, None),
        row("y", 10.0, 0.5),
        row("z", 20.0, 0.7),
        row("f", 0, 0, failed=True),
    ]
    assert [r["label"] for r in sort_rows(rows, "mpjpe_mm")] == ["z", "y", "x", "f"]


def test_scene_args_reopen_the_batch_results():
    base = argparse.Namespace(scene=None, out=None, config=None, set=[], frame=None, track=None,
                              force=True, batch="dir", rerun=True, port=1)  # fmt: skip
    r = dict(row("a", 1.0, 1.0), set_args=["kalman.q=5"])
    ns = scene_args(base, r, r["summary"]["worst"][0])
    assert (str(ns.scene), str(ns.out), ns.set, ns.frame, ns.track) == (
        "/data/a",
        "/data/a/.mvviz/results.npz",
        ["kalman.q=5"],
        3,
        1,
    )
    assert not ns.force and ns.batch is None and not ns.rerun and ns.port == 1
    assert first_row(build_report([row("p", 1.0, 1.0), row("q", 5.0, 1.0)]))["label"] == "q"


# --------------------------------------------------------------------------- browser


@pytest.fixture(scope="module")
def batch_dir(tmp_path_factory):
    """A report of two tiny scenes (different seeds and lengths), made with the batch's
    own functions (no Ray needed for the viewer)."""
    base = tmp_path_factory.mktemp("dataset")
    model = load_body_model()
    cfg = PipelineConfig(fit_smpl=False)
    rows = []
    for name, frames, seed in (("walk_a", 10, 4), ("walk_b", 14, 9)):
        d = base / name
        synth = SynthConfig(num_people=2, num_frames=frames, seed=seed, render_video=False)
        write_synth_scene(d, campus_rig(), model, synth, progress=False)
        scene = load_scene(d)
        results = run_pipeline(scene, cfg, model, progress=False)
        assert results.cache_key == cache_key(scene, cfg, model)
        path = d / ".mvviz" / "results.npz"
        save_results(results, path)
        rows.append({
            "scene": str(d), "label": name, "setting": [], "set_args": ["fit_smpl=false"],
            "config_file": None, "status": "computed", "error": None, "results": str(path),
            "summary": summarize(scene, results), "seconds": 0.0,
        })  # fmt: skip
    write_report(build_report(rows), base)
    return base


def page_text(page) -> str:
    return page.evaluate("() => document.body.textContent")


@pytest.mark.slow
def test_app_batch_switches_scenes_in_chromium(batch_dir, tmp_path):
    # Playwright's sync API refuses a thread where an asyncio loop is marked running
    # (an earlier test in the session can leave one); a fresh thread has none.
    with ThreadPoolExecutor(1) as pool:
        pool.submit(_switch_scenes_in_chromium, batch_dir, tmp_path).result()


def _switch_scenes_in_chromium(batch_dir, tmp_path):
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is absent")
    sync_api = pytest.importorskip("playwright.sync_api")
    port = free_port()
    args = argparse.Namespace(
        scene=None, batch=batch_dir, port=port, host="127.0.0.1", smpl_model=None, config=None,
        set=[], out=None, force=False, frame=None, track=None, rerun=False,
    )  # fmt: skip
    viewer = start_batch(args, progress=False)
    try:
        first = viewer.shown
        worst = first["summary"]["worst"][0]
        assert viewer.app.state.frame == worst["frame"]
        other = next(r for r in viewer.report["rows"] if r["label"] != first["label"])
        with sync_api.sync_playwright() as pw:
            browser = launch_chromium(pw)
            page = browser.new_page(viewport={"width": 1400, "height": 860})
            page.goto(viewer.app.url)
            page.wait_for_selector("canvas", timeout=60_000)
            close_webgl_notice(page)
            # The Dataset tab is the open one, before and after a switch: the page
            # reconnects to each new scene's viewer and stays on the list.
            dataset_tab = page.get_by_role("tab", name="Dataset")
            assert dataset_tab.get_attribute("aria-selected") == "true"
            page.wait_for_timeout(1500)
            assert f"▶ {first['label']}" in page_text(page)
            page.screenshot(path=str(tmp_path / "dataset_before.png"))
            page.get_by_role("button", name=f"{other['label']} ·").click()
            assert viewer.switched.wait(120), "the other scene did not open"
            want = other["summary"]["worst"][0]["frame"]
            n = other["summary"]["num_frames"]
            page.wait_for_function(
                "t => document.body.textContent.includes(t)", arg=f"frame {want} / {n - 1}",
                timeout=60_000,
            )  # fmt: skip
            deadline = time.time() + 30
            while f"▶ {other['label']}" not in page_text(page) and time.time() < deadline:
                page.wait_for_timeout(300)
            assert f"▶ {other['label']}" in page_text(page)
            assert page.get_by_role("tab", name="Dataset").get_attribute("aria-selected") == "true"
            assert viewer.app.state.data.scene.root.name == other["label"]
            assert viewer.app.server.get_port() == port  # the page reconnected to it
            page.wait_for_timeout(1500)
            page.screenshot(path=str(tmp_path / "dataset_after.png"))
            browser.close()
    finally:
        viewer.stop()
    print("screenshots:", tmp_path / "dataset_before.png", tmp_path / "dataset_after.png")
