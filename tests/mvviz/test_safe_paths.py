"""Files the viewer writes on a page's request stay where they belong: a typed name is a
file inside its folder (:func:`mvviz.safe_paths.resolve_inside`), and a viewer served on
anything but loopback is read-only unless ``--allow-writes``, refused server-side
whatever the page sends (:class:`mvviz.safe_paths.WritePolicy`, ``mvviz view``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from mvviz.cli import build_parser
from mvviz.cli.view import start, stop
from mvviz.safe_paths import WritePolicy, WriteRefused, is_loopback, resolve_inside
from tests.mvviz.conftest import free_port


@pytest.fixture
def root(tmp_path) -> Path:
    r = tmp_path / "exports"
    r.mkdir()
    return r


# --------------------------------------------------------------------------- resolve_inside


@pytest.mark.parametrize(
    "name, why",
    [
        ("../x", "leads out of"),
        ("a/../../x", "leads out of"),
        ("..", "leads out of"),
        (".", "is the folder"),
        ("a/..", "is the folder"),
        ("/etc/x", "is an absolute path"),
        ("~/x", "`~` is not a folder here"),
        ("~", "`~` is not a folder here"),
        ("", "give a file name"),
        ("  ", "give a file name"),
        ("a\0b", "give a file name"),
    ],
)
def test_names_leading_out_are_refused(root, name, why):
    with pytest.raises(WriteRefused) as err:
        resolve_inside(root, name, overwrite=True)
    assert why in str(err.value) and len(str(err.value).splitlines()) == 1
    assert list(root.iterdir()) == []


def test_names_inside_resolve_to_files_inside(root):
    assert resolve_inside(root, "x.glb", overwrite=False) == root / "x.glb"
    assert resolve_inside(root, "sub/dir/x.glb", overwrite=False) == root / "sub" / "dir" / "x.glb"
    assert resolve_inside(root, "a/../x.glb", overwrite=False) == root / "x.glb"
    assert resolve_inside(str(root), Path("x.glb"), overwrite=False) == root / "x.glb"
    assert list(root.iterdir()) == []  # nothing is created by asking


def test_symlinks_out_of_the_folder_are_refused(root, tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "victim.txt").write_text("keep")
    (root / "dir").symlink_to(outside, target_is_directory=True)
    (root / "file.txt").symlink_to(outside / "victim.txt")
    (root / "dangling.txt").symlink_to(outside / "new.txt")
    for name in ("dir/x.txt", "dir/victim.txt", "file.txt", "dangling.txt"):
        with pytest.raises(WriteRefused, match="follows a symlink out of"):
            resolve_inside(root, name, overwrite=True)
    assert sorted(p.name for p in outside.iterdir()) == ["victim.txt"]


def test_a_symlink_inside_the_folder_is_followed(root):
    (root / "runs").mkdir()
    (root / "latest").symlink_to(root / "runs", target_is_directory=True)
    assert resolve_inside(root, "latest/x.glb", overwrite=False) == root / "runs" / "x.glb"


def test_a_symlink_loop_is_refused(root):
    (root / "a").symlink_to(root / "b")
    (root / "b").symlink_to(root / "a")
    with pytest.raises(WriteRefused):
        resolve_inside(root, "a", overwrite=True)


def test_an_existing_file_needs_overwrite(root):
    (root / "x.trc").write_text("mine")
    with pytest.raises(WriteRefused, match="exists.*tick Overwrite"):
        resolve_inside(root, "x.trc", overwrite=False)
    assert resolve_inside(root, "x.trc", overwrite=True) == root / "x.trc"
    assert (root / "x.trc").read_text() == "mine"  # resolving never writes


def test_the_folder_may_not_exist_yet(tmp_path):
    assert resolve_inside(tmp_path / "new", "x", overwrite=False) == tmp_path / "new" / "x"
    assert not (tmp_path / "new").exists()


# --------------------------------------------------------------------------- hosts


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.0.2", "localhost", "LocalHost", "::1"])
def test_loopback_hosts(host):
    assert is_loopback(host)
    assert WritePolicy.for_host(host, "x").read_only is None


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "", "192.168.1.20", "example.org"])
def test_other_hosts_are_read_only_unless_allowed(host, root):
    assert not is_loopback(host)
    policy = WritePolicy.for_host(host, root)
    assert policy.read_only is not None and "--allow-writes" in policy.read_only
    with pytest.raises(WriteRefused, match="read-only"):
        policy.export_file("x.glb", overwrite=True)
    with pytest.raises(WriteRefused, match="read-only"):
        policy.scene_file(root, "mvviz_config.json")
    allowed = WritePolicy.for_host(host, root, allow_writes=True)
    assert allowed.read_only is None
    assert allowed.export_file("x.glb", overwrite=False) == root / "x.glb"


# --------------------------------------------------------------------------- the viewer


def test_a_viewer_on_a_non_loopback_host_is_read_only(viewer_scene, tmp_path, capsys):
    """``mvviz view --host 0.0.0.0``: the warning on stderr, the page's line, every
    write button disabled, and each write refused when its callback is called anyway
    (a page can send a click on a disabled button): nothing is written."""
    scene = viewer_scene[0]
    exports = tmp_path / "exports"
    argv = ["view", str(scene.root), "--port", str(free_port()), "--host", "0.0.0.0"]
    app = start(build_parser(argv).parse_args([*argv, "--export-dir", str(exports)]))
    try:
        err = capsys.readouterr().err
        assert "warning: serving on 0.0.0.0: the viewer has no authentication" in err
        assert "(read-only)" in err
        line = app.read_only_line.content
        assert "read-only" in line and "--allow-writes" in line and "\n" not in line
        ex, pl = app.export_panel, app.pipeline_panel
        fp, fl = app.filter_panel, app.failure_panel
        for button in (ex.gui.export, pl.gui.save, pl.gui.export, fp.gui.apply, fl.gui.flag):
            assert button.disabled
        config = scene.root / "mvviz_config.json"
        notes = fl.notes_file
        before = (config.exists(), notes.exists())
        ex.gui.path.value = "run.glb"
        ex.gui.export.value = True  # runs the click's callback, as a page's click does
        assert ex.gui.status.content.startswith("export refused: read-only")
        pl.gui.export.value = True
        assert pl.gui.export_status.content.startswith("export refused: read-only")
        pl.gui.save.value = True
        assert pl.gui.status.content.startswith("not saved: read-only")
        fp.gui.apply.value = True
        assert fp.message.startswith("Apply B failed: read-only")
        fl.gui.note_text.value = "a note"
        fl.gui.flag.value = True
        assert "**not saved:** read-only" in fl.gui.notes_info.content
        assert ex.wait(10) and pl.wait_idle(60)
        assert not exports.exists() and (config.exists(), notes.exists()) == before
    finally:
        stop(app)


def test_allow_writes_lets_a_non_loopback_viewer_write(viewer_scene, tmp_path, capsys):
    scene = viewer_scene[0]
    exports = tmp_path / "exports"
    argv = ["view", str(scene.root), "--port", str(free_port()), "--host", "0.0.0.0"]
    args = build_parser(argv).parse_args([*argv, "--export-dir", str(exports), "--allow-writes"])
    app = start(args)
    try:
        err = capsys.readouterr().err
        assert "no authentication" in err and "(writes allowed (--allow-writes))" in err
        assert app.read_only_line is None and not app.export_panel.gui.export.disabled
        app.export_panel.export(fmt="trc", stage="raw", path="t.trc")
        assert app.export_panel.wait(60)
        assert [f.path for f in app.export_panel.last_files] == [exports.resolve() / "t.trc"]
    finally:
        stop(app)


def test_a_loopback_viewer_prints_no_warning(viewer_scene, capsys):
    argv = ["view", str(viewer_scene[0].root), "--port", str(free_port())]
    app = start(build_parser(argv).parse_args(argv))
    try:
        assert "warning" not in capsys.readouterr().err
        assert app.writes.read_only is None and app.read_only_line is None
        assert app.writes.export_dir == viewer_scene[0].root / ".mvviz" / "export"
    finally:
        stop(app)
