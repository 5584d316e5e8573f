"""Files the viewer writes on a page's request stay where they belong: a typed name is a
file inside its folder (:func:`mvviz.safe_paths.resolve_inside`), and a viewer served on
anything but loopback is read-only unless ``--allow-writes``, refused server-side
whatever the page sends (:class:`mvviz.safe_paths.WritePolicy`, ``mvviz view``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from mvviz.safe_paths import WritePolicy, WriteRefused, is_loopback, resolve_inside


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
