"""The viewer's "Export" panel: its choices follow the run, it writes what ``mvviz
export`` writes, and reports the files and notes (or the refusal) in its status. A name
typed in the panel is a file inside the export folder: one leading out of it, or naming
an existing file while "Overwrite" is off, is refused in the status line and nothing is
written (``mvviz/safe_paths.py``)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from mvviz.panels.export_panel import LAST, stage_options, track_options
from pipeline.exports.gltf import read_glb


@pytest.fixture
def folder(running_app, tmp_path):
    """A subfolder of the shared viewer's export folder that only this test uses; the
    panel's controls are put back afterwards."""
    yield tmp_path.name
    g = running_app.export_panel.gui
    g.format.value, g.overwrite.value, g.per_track.value = "glb", False, False
    g.stage.value, g.track.value = LAST, "all"
    g.path.value = f"{running_app.state.scene.name}.glb"


def export_dir(app) -> Path:
    return Path(app.writes.export_dir).resolve()


def test_choices_follow_the_format_and_the_run(running_app):
    panel = running_app.export_panel
    results = running_app.state.results
    g = panel.gui
    assert g.format.value == "glb" and g.stage.options == stage_options(results, "glb")
    assert g.stage.options == (LAST, "smpl", "smpl_vae")
    assert g.track.options == track_options(results)
    assert g.path.value == f"{running_app.state.scene.name}.glb"  # a name, not a path
    g.format.value = "trc"
    panel._choices_changed()  # what the dropdown's callback does
    assert g.stage.options == (LAST, "raw", "kalman", "rts", "smpl", "smpl_vae")
    assert g.path.value.endswith(".trc")
    g.format.value = "glb"
    panel._choices_changed()
    assert g.path.value.endswith(".glb")


def test_export_writes_the_files_and_reports_them(running_app, folder):
    panel = running_app.export_panel
    results = running_app.state.results
    out = export_dir(running_app) / folder
    panel.export(fmt="glb", stage=LAST, track="all", path=f"{folder}/v.glb")
    assert panel.wait(60)
    assert "wrote 1 file(s)" in panel.gui.status.content and "`v.glb`" in panel.gui.status.content
    doc, _ = read_glb(out / "v.glb")
    assert len(doc["skins"]) == int(results.smpl_vae.present.any(1).sum())
    panel.export(fmt="trc", stage="raw", track="0", path=f"{folder}/t.trc", per_track=False)
    assert panel.wait(60)
    assert [f.path for f in panel.last_files] == [out / "t.trc"]
    assert np.isfinite(np.loadtxt(out / "t.trc", skiprows=6, usecols=1)).all()
    assert sorted(p.name for p in out.iterdir()) == ["t.trc", "v.glb"]  # no staging left


def test_a_refused_export_says_why(running_app, folder):
    panel = running_app.export_panel
    panel.export(fmt="bvh", stage="raw", track="all", path=f"{folder}/x.bvh")
    assert panel.wait(60)
    assert panel.gui.status.content.startswith("export failed: bvh holds fitted bodies")
    assert list((export_dir(running_app) / folder).iterdir()) == []


def click_export(panel, name: str, *, overwrite: bool = False) -> None:
    """What a page does: type the name, set Overwrite, click Export (the callbacks run
    at once, on this thread); then wait for a started export to end."""
    panel.gui.path.value = name
    panel.gui.overwrite.value = overwrite
    panel.gui.export.value = True
    assert panel.wait(60)


@pytest.mark.parametrize(
    "name, why",
    [
        ("../escaped.trc", "leads out of"),
        ("sub/../../escaped.trc", "leads out of"),
        ("/tmp/escaped.trc", "is an absolute path"),
        ("~/escaped.trc", "`~` is not a folder here"),
        ("", "give a file name"),
    ],
)
def test_a_name_leading_out_of_the_folder_is_refused(running_app, folder, name, why):
    panel = running_app.export_panel
    root = export_dir(running_app)
    panel.gui.format.value = "trc"
    before = sorted(root.rglob("*")) if root.exists() else []
    click_export(panel, name)
    status = panel.gui.status.content
    assert status.startswith("export refused: ") and why in status, status
    assert len(status.splitlines()) == 1 and panel.last_files == []
    for where in (root.parent, Path("/tmp"), Path.home()):
        assert not (where / "escaped.trc").exists()
    assert (sorted(root.rglob("*")) if root.exists() else []) == before


def test_a_symlink_out_of_the_folder_is_refused(running_app, folder, tmp_path):
    panel = running_app.export_panel
    outside = tmp_path / "outside"
    outside.mkdir()
    inside = export_dir(running_app) / folder
    inside.mkdir(parents=True)
    (inside / "link").symlink_to(outside, target_is_directory=True)
    (inside / "file.trc").symlink_to(outside / "target.trc")  # dangling, pointing out
    panel.gui.format.value = "trc"
    for name in (f"{folder}/link/x.trc", f"{folder}/file.trc"):
        click_export(panel, name, overwrite=True)
        status = panel.gui.status.content
        assert status.startswith("export refused: ") and "follows a symlink out of" in status
    assert list(outside.iterdir()) == []
    assert sorted(p.name for p in inside.iterdir()) == ["file.trc", "link"]


def test_an_existing_file_needs_overwrite(running_app, folder):
    panel = running_app.export_panel
    out = export_dir(running_app) / folder
    out.mkdir(parents=True)
    (out / "t.trc").write_text("mine")
    panel.gui.format.value = "trc"
    panel.gui.stage.value = "raw"
    click_export(panel, f"{folder}/t.trc")
    status = panel.gui.status.content
    assert status.startswith("export refused: ") and "exists" in status and "Overwrite" in status
    assert (out / "t.trc").read_text() == "mine"
    click_export(panel, f"{folder}/t.trc", overwrite=True)
    assert "wrote 1 file(s)" in panel.gui.status.content
    assert (out / "t.trc").read_text().startswith("PathFileType")
    assert sorted(os.listdir(out)) == ["t.trc"]


def test_per_track_files_that_exist_need_overwrite_too(running_app, folder):
    """The typed name is new but a per-track file beside it is not: nothing is written."""
    panel = running_app.export_panel
    out = export_dir(running_app) / folder
    out.mkdir(parents=True)
    (out / "p_track1.trc").write_text("mine")
    panel.export(fmt="trc", stage="raw", track="all", path=f"{folder}/p.trc", per_track=True)
    assert panel.wait(60)
    status = panel.gui.status.content
    assert status.startswith("export refused: ") and "p_track1.trc" in status, status
    assert sorted(os.listdir(out)) == ["p_track1.trc"] and panel.last_files == []
    assert (out / "p_track1.trc").read_text() == "mine"
    panel.export(
        fmt="trc", stage="raw", track="all", path=f"{folder}/p.trc", per_track=True,
        overwrite=True,
    )  # fmt: skip
    assert panel.wait(60)
    assert "p_track1.trc" in [f.path.name for f in panel.last_files]
    assert len(panel.last_files) >= 2 and (out / "p_track1.trc").read_text() != "mine"
