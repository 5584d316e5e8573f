"""The viewer's "Export" panel: its choices follow the run, it writes what ``mvviz
export`` writes, and reports the files and notes (or the refusal) in its status."""

from __future__ import annotations

import numpy as np

from mvviz.panels.export_panel import LAST, stage_options, track_options
from pipeline.exports.gltf import read_glb


def test_choices_follow_the_format_and_the_run(running_app):
    panel = running_app.export_panel
    results = running_app.state.results
    g = panel.gui
    assert g.format.value == "glb" and g.stage.options == stage_options(results, "glb")
    assert g.stage.options == (LAST, "smpl", "smpl_vae")
    assert g.track.options == track_options(results)
    g.format.value = "trc"
    panel._choices_changed()  # what the dropdown's callback does
    assert g.stage.options == (LAST, "raw", "kalman", "rts", "smpl", "smpl_vae")
    assert g.path.value.endswith(".trc")
    g.format.value = "glb"
    panel._choices_changed()
    assert g.path.value.endswith(".glb")


def test_export_writes_the_files_and_reports_them(running_app, tmp_path):
    panel = running_app.export_panel
    results = running_app.state.results
    panel.export(fmt="glb", stage=LAST, track="all", path=tmp_path / "v.glb")
    assert panel.wait(60)
    assert "wrote 1 file(s)" in panel.gui.status.content and "`v.glb`" in panel.gui.status.content
    doc, _ = read_glb(tmp_path / "v.glb")
    assert len(doc["skins"]) == int(results.smpl_vae.present.any(1).sum())
    panel.export(fmt="trc", stage="raw", track="0", path=tmp_path / "t.trc", per_track=False)
    assert panel.wait(60)
    assert [f.path.name for f in panel.last_files] == ["t.trc"]
    assert np.isfinite(np.loadtxt(tmp_path / "t.trc", skiprows=6, usecols=1)).all()


def test_a_refused_export_says_why(running_app, tmp_path):
    panel = running_app.export_panel
    panel.export(fmt="bvh", stage="raw", track="all", path=tmp_path / "x.bvh")
    assert panel.wait(60)
    assert panel.gui.status.content.startswith("export failed: bvh holds fitted bodies")
    assert list(tmp_path.iterdir()) == []
