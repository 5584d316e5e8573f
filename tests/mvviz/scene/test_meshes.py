"""Meshes that stay interactive: decimated display bodies, solid / translucent /
wireframe styles, the selected track's body only, and the software-WebGL notice; in
process (the viser handles) and in headless chromium (frame rate, click latency, and
screenshots of each mode).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mvviz.app import ViewerApp
from mvviz.scene.decimate import cluster_vertices, decimate_bodies
from mvviz.scene.geometry import MESH_OPACITY, frame_geometry, gt_person_of
from mvviz.state import ViewerState
from tests.mvviz.conftest import free_port, open_viewer, settle, wait_rendered

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(scope="module")
def app(viewer_scene, frame_store):
    scene, results, model = viewer_scene
    state = ViewerState.create(scene, results, model)
    a = ViewerApp(state, host="127.0.0.1", port=free_port(), frames=frame_store)
    assert a.wait_idle(30)
    yield a
    a.stop()


def set_layers(app: ViewerApp, **values) -> None:
    """What the Layers panel's controls do, then wait for the render."""
    panel = app.layers_panel.gui
    for name, value in values.items():
        if name in panel.toggles:
            panel.toggles[name].value = value
        else:
            getattr(panel, name).value = value
    assert app.wait_idle(30)


def test_decimation_keeps_the_body(viewer_state):
    """About a sixth of the faces; every cluster vertex near the full surface; weights
    still sum to one; bone poses untouched."""
    b = viewer_state.data.bodies
    d = decimate_bodies(b)
    assert d.faces.shape[0] < b.faces.shape[0] / 4 and d.vertices.shape[1] < b.vertices.shape[1] / 4
    assert d.faces.max() < d.vertices.shape[1] and d.vertices.shape[0] == b.vertices.shape[0]
    np.testing.assert_allclose(d.weights.sum(1), 1.0, atol=1e-5)
    assert d.bone_wxyz is b.bone_wxyz and d.present is b.present
    # each decimated vertex lies within a cell (3 cm) of the full surface of its body
    for i in range(len(b.ids)):
        nearest, _ = cKDTree(b.vertices[i]).query(d.vertices[i])
        assert np.percentile(nearest, 95) < 0.015 and nearest.max() < 0.03
    # clustering: faces that collapse are dropped, windings kept
    v = np.array([[0, 0, 0], [0.001, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    c = cluster_vertices(v, np.array([[0, 2, 3], [1, 2, 3], [0, 1, 2]]), 0.01)
    assert c.num_clusters == 3 and c.labels[0] == c.labels[1]
    assert c.faces.tolist() == [c.labels[[0, 2, 3]].tolist()]  # one face left, same winding
    with pytest.raises(ValueError, match="cell"):
        cluster_vertices(v, c.faces, 0.0)


def test_mesh_modes_on_the_viser_handles(app):
    data = app.state.data
    full_v = data.bodies.vertices.shape[1]
    set_layers(app, meshes=True, fit_meshes=True)
    try:
        gt, fit = app.layers.meshes, app.layers.fit_meshes
        assert gt and fit
        # decimated by default; both solid layers: the ground truth translucent
        assert all(len(m.vertices) < full_v / 4 for m in (*gt.values(), *fit.values()))
        assert all(m.opacity == MESH_OPACITY for m in gt.values())
        assert not any(m.wireframe or m.opacity for m in fit.values())
        set_layers(app, mesh_style="translucent")
        assert all(m.opacity == MESH_OPACITY and not m.wireframe for m in fit.values())
        assert all(m.opacity == MESH_OPACITY for m in gt.values())
        decimated_v = len(next(iter(app.layers.fit_meshes.values())).vertices)
        set_layers(app, mesh_style="wireframe")
        gt, fit = app.layers.meshes, app.layers.fit_meshes
        assert all(m.wireframe for m in (*gt.values(), *fit.values()))
        # a coarser mesh for the wireframe (software WebGL draws lines slowly)
        assert all(len(m.vertices) < decimated_v / 2 for m in fit.values())
        # the full mesh on request: same node names, replaced in place
        names = sorted(m.name for m in fit.values())
        set_layers(app, mesh_detail="full")
        fit = app.layers.fit_meshes
        assert sorted(m.name for m in fit.values()) == names
        assert all(len(m.vertices) == full_v for m in fit.values())
        assert all(m.wireframe for m in fit.values())  # the style carries over
        # only the selected track's body, and its ground-truth person's
        app.jump_to(frame=6, track=1)
        set_layers(app, meshes_selected_only=True)
        shown = [k for k, m in app.layers.fit_meshes.items() if m.visible]
        assert shown == [1]
        pid = gt_person_of(data, 1, 6)
        assert [p for p, m in app.layers.meshes.items() if m.visible] == [pid]
        geom = frame_geometry(app.state)
        assert set(geom.fit_meshes) == {1} and set(geom.meshes) == {pid}
        assert not app.render_errors
    finally:
        set_layers(
            app, meshes=False, fit_meshes=False, meshes_selected_only=False,
            mesh_style="solid", mesh_detail="decimated",
        )  # fmt: skip


def test_toggles_a_scene_cannot_show_are_disabled(viewer_scene):
    scene, results, model = viewer_scene
    no_gt = dataclasses.replace(scene, gt=None)
    state = ViewerState.create(no_gt, results, model)
    a = ViewerApp(state, host="127.0.0.1", port=free_port())
    try:
        t = a.layers_panel.gui.toggles
        assert t["gt"].disabled and not t["gt"].value and not state.layers.gt
        assert t["meshes"].disabled and not t["fit_meshes"].disabled
    finally:
        a.stop()


def frame_rate(page, seconds: float = 4.0) -> float:
    """Frames the page draws per second (requestAnimationFrame callbacks)."""
    return page.evaluate(
        """s => new Promise(done => {
            let n = 0; const t0 = performance.now();
            const tick = () => { n++;
                if (performance.now() - t0 < s * 1000) requestAnimationFrame(tick);
                else done(n * 1000 / (performance.now() - t0)); };
            requestAnimationFrame(tick); })""",
        seconds,
    )


def click_latency(app, page) -> float:
    """Seconds from a click on "+1 ▶" until the server has the next frame."""
    f = app.state.frame
    t0 = time.monotonic()
    page.get_by_role("button", name="+1 ▶").click(timeout=120_000)
    while app.state.frame != f + 1 and time.monotonic() - t0 < 120:
        time.sleep(0.02)
    return time.monotonic() - t0


@pytest.mark.slow
def test_meshes_stay_interactive_in_software_webgl(browser, app, tmp_path):
    """In headless chromium (SwiftShader): the software notice shows; frame rate and a
    click's latency with both mesh layers, full and solid (the old default) against the
    decimated wireframe / translucent modes and the selected track only. Screenshots
    of each mode are kept in tmp_path."""
    page = open_viewer(browser, app.url)
    figures = {}
    try:
        notice = page.locator(".mvviz-software-gl")
        notice.wait_for(state="visible", timeout=20_000)
        assert "Software WebGL" in notice.inner_text()
        app.jump_to(frame=10, track=0)
        wait_rendered(app, page)
        figures["no meshes"] = (frame_rate(page), click_latency(app, page))
        modes = {
            "full, solid": dict(mesh_detail="full", mesh_style="solid"),
            "decimated, solid": dict(mesh_detail="decimated", mesh_style="solid"),
            "decimated, translucent": dict(mesh_style="translucent"),
            "decimated, wireframe": dict(mesh_style="wireframe"),
            "selected track, solid": dict(mesh_style="solid", meshes_selected_only=True),
        }
        set_layers(app, meshes=True, fit_meshes=True)
        for name, values in modes.items():
            set_layers(app, **values)
            wait_rendered(app, page, 3)
            page.screenshot(path=str(tmp_path / f"meshes_{name.replace(', ', '_')}.png"))
            figures[name] = (frame_rate(page), click_latency(app, page))
        print("\nmode: frames/s in the page, click -> server (s)")
        for name, (fps, click) in figures.items():
            print(f"  {name:<24s} {fps:5.1f} fps  {click:5.2f} s")
        # every mode draws and answers a click. Which mode draws faster is printed, not
        # asserted: two 4 s samples one after the other on a shared machine are not a
        # comparison (a speed target is a benchmark's). The decimation itself is checked
        # on the handles (test_mesh_modes_on_the_viser_handles).
        assert all(fps > 0 for fps, _ in figures.values()), figures
        assert all(click < 30 for _, click in figures.values()), figures
    finally:
        set_layers(
            app, meshes=False, fit_meshes=False, meshes_selected_only=False,
            mesh_style="solid", mesh_detail="decimated",
        )  # fmt: skip
        settle(page, 0.5)
        page.close()
