"""Where the viewer may write what a browser asks for, and whether it may write at all.

A path typed in the browser is a name inside one folder fixed when the viewer starts
(the export folder: ``--export-dir``, default ``SCENE/.mvviz/export``);
:func:`resolve_inside` turns it into the file to write, or refuses it with a one-line
:class:`WriteRefused`: a name that leads out of the folder (``../x``, an absolute path,
``~/x``, a symlink pointing out), the folder itself, or an existing file unless
``overwrite``. Files with fixed names (the saved config, notes, results) go through it
too, under the scene folder.

A viewer served on anything but loopback starts read-only (:meth:`WritePolicy.for_host`):
every write is refused server-side, whatever a page sends, unless ``--allow-writes``.
"""

from __future__ import annotations

import ipaddress
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

LOOPBACK_NAMES = ("localhost",)


class WriteRefused(ValueError):
    """A write the viewer will not do; the message is one line, for the panel."""


def resolve_inside(root: str | os.PathLike, name: str | os.PathLike, *, overwrite: bool) -> Path:
    """The file ``name`` names inside the folder ``root``, symlinks resolved.

    Raises :class:`WriteRefused` if ``name`` is empty, absolute or starts with ``~``, if
    it resolves to ``root`` itself or outside it (``..`` or a symlink on the way, the
    file's own included), or if it names an existing file and not ``overwrite``.
    """
    text = os.fspath(name).strip()
    if not text or "\0" in text:
        raise WriteRefused(f"give a file name inside `{root}`")
    if text.startswith("~"):
        raise WriteRefused(f"`{text}`: `~` is not a folder here; give a name inside `{root}`")
    rel = Path(text)
    if rel.is_absolute():
        raise WriteRefused(f"`{text}` is an absolute path; give a name inside `{root}`")
    base = Path(root).resolve()
    try:
        target = (base / rel).resolve()  # follows every symlink on the way, the last one too
    except (OSError, RuntimeError) as exc:  # a symlink loop
        raise WriteRefused(f"`{text}`: {exc}") from None
    if target == base:
        raise WriteRefused(f"`{text}` is the folder `{root}` itself; give a file name in it")
    if not target.is_relative_to(base):
        lexical = Path(os.path.normpath(base / rel))
        how = "follows a symlink" if lexical.is_relative_to(base) else "leads"
        raise WriteRefused(f"`{text}` {how} out of `{root}`")
    if not overwrite and target.exists():
        raise WriteRefused(f"`{text}` exists in `{root}`; tick Overwrite to replace it")
    return target


def cannot_write(folder: str | os.PathLike) -> str | None:
    """Why no file can be created in the existing ``folder`` (None: one can), tried (as
    ``pipeline.core.files.cannot_write``, which this module may not import)."""
    try:
        fd, probe = tempfile.mkstemp(prefix=".mvviz-probe.", dir=folder)
    except OSError as exc:
        return exc.strerror or type(exc).__name__
    os.close(fd)
    os.unlink(probe)
    return None


def shown_path(path: str | os.PathLike, scene_root: str | os.PathLike) -> str:
    """``SCENE/<path inside the scene>``, or the whole path when it is elsewhere."""
    path, root = Path(path), Path(scene_root)
    return f"SCENE/{path.relative_to(root)}" if path.is_relative_to(root) else str(path)


def is_loopback(host: str) -> bool:
    """``host`` (an address to bind) reaches this machine only: 127.0.0.0/8, ::1, localhost."""
    if host.strip().lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip().strip("[]")).is_loopback
    except ValueError:
        return False  # a host name, "" or 0.0.0.0-like: other machines may reach it


@dataclass(frozen=True)
class WritePolicy:
    """Where browser-requested files go (``export_dir``) and, when the viewer writes
    nothing, why (``read_only``: one line, shown on the page)."""

    export_dir: Path
    read_only: str | None = None

    @classmethod
    def for_host(
        cls, host: str, export_dir: str | os.PathLike, *, allow_writes: bool = False
    ) -> WritePolicy:
        """Writes allowed on loopback or with ``allow_writes``; read-only otherwise."""
        reason = None
        if not (allow_writes or is_loopback(host)):
            reason = (
                f"read-only: served on {host or 'every address'} with no authentication, "
                "so exports and saves are off (start with --allow-writes to allow them)"
            )
        return cls(Path(export_dir), reason)

    def check(self) -> None:
        """Raise :class:`WriteRefused` when the viewer is read-only."""
        if self.read_only is not None:
            raise WriteRefused(self.read_only)

    def export_file(self, name: str | os.PathLike, *, overwrite: bool) -> Path:
        """The file a typed ``name`` names in the export folder (refused when read-only)."""
        self.check()
        return resolve_inside(self.export_dir, name, overwrite=overwrite)

    def scene_file(self, scene_root: str | os.PathLike, name: str | os.PathLike) -> Path:
        """A file of fixed ``name`` under the scene folder, replaced when it exists
        (refused when read-only, when a symlink leads it out of the scene, or when its
        folder cannot be written: a read-only scene)."""
        self.check()
        path = resolve_inside(scene_root, name, overwrite=True)
        folder = next((p for p in (path.parent, *path.parent.parents) if p.is_dir()), None)
        why = None if folder is None else cannot_write(folder)
        if why is not None:
            raise WriteRefused(f"`{folder}` cannot be written ({why})")
        return path

    def cache_file(self, scene_root: str | os.PathLike, path: str | os.PathLike) -> Path:
        """``path``, a file of fixed name in the scene's cache folder
        (:func:`~pipeline.core.files.scene_cache_dir`): under the scene, checked as
        :meth:`scene_file`; in the user's cache (a read-only scene) as it is."""
        path, root = Path(path), Path(scene_root)
        if path.is_relative_to(root):
            return self.scene_file(root, path.relative_to(root))
        self.check()
        return path
