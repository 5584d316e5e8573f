"""File plumbing shared by every reader and writer: format errors and atomic writes.

Every output the project writes goes through :func:`atomic_write` or
:func:`atomic_directory`, so an interrupted or failed write never leaves a
half-written file or scene behind.

Temporary names carry the writer's process id: ``.NAME.<pid>.<random>.tmp`` beside
``NAME``. A process killed mid-write (SIGKILL runs no cleanup) leaves one behind; the
next write of ``NAME`` (and :func:`recover`, which :func:`~pipeline.data.scene.load_scene`
calls) removes those of dead processes. Replacing a directory takes two renames
(``NAME -> .NAME.old-<pid>``, then ``.NAME.new-<pid> -> NAME``); a kill between them
is completed by :func:`recover`: the complete new directory is put in place (the old
one is restored only if the new one is gone), so afterwards either the old or the new
directory is at ``NAME``, whole.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import re
import shutil
import sys
import tempfile
import tomllib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

CACHE_DIR = ".mvviz"
"""``SCENE/.mvviz/``: what mvviz computes for a scene (results, caches, notes, exports);
:func:`scene_cache_dir` says where it is for a scene whose folder cannot be written."""
CACHE_ENV = "MVVIZ_CACHE_DIR"  # the user cache's folder (default: XDG_CACHE_HOME/mvviz)
_OWN_CACHE: dict[Path, Path | None] = {}  # resolved scene root -> its fallback (None: in it)


def user_cache_root() -> Path:
    """``$MVVIZ_CACHE_DIR``, else ``$XDG_CACHE_HOME/mvviz``, else ``~/.cache/mvviz``."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "mvviz"


PROBE_PREFIX = ".mvviz-probe."


def cannot_write(folder: str | os.PathLike) -> str | None:
    """Why no file can be created in the existing ``folder`` (None: one can). Tried, not
    guessed from the mode bits: a read-only mount, another user's folder and root's
    capabilities all answer for themselves."""
    try:
        fd, probe = tempfile.mkstemp(prefix=PROBE_PREFIX, dir=folder)
    except OSError as exc:
        return exc.strerror or type(exc).__name__
    os.close(fd)
    # A probe lives between two system calls; one found here is a killed process's
    # (or, harmlessly, one being removed this instant: its own unlink tolerates that).
    for stale in Path(folder).glob(PROBE_PREFIX + "*"):
        with contextlib.suppress(OSError):
            stale.unlink()
    return None


def scene_cache_dir(root: str | os.PathLike) -> Path:
    """Where mvviz keeps what it computes for the scene at ``root``: ``root/.mvviz``, or,
    when that cannot be written (a read-only folder or mount, another user's scene), a
    folder of the scene's own in the user's cache (:func:`user_cache_root`/scenes/
    ``<name>-<hash of the path>``), said once on stderr. Decided once per scene and
    process; nothing is created in the scene to decide."""
    root = Path(root)
    key = root.resolve()
    if key not in _OWN_CACHE:
        own = root / CACHE_DIR
        why = cannot_write(own if own.is_dir() else root) if root.is_dir() else None
        fallback = None
        if why is not None:
            digest = hashlib.sha1(str(key).encode()).hexdigest()[:12]
            fallback = user_cache_root() / "scenes" / f"{key.name}-{digest}"
            print(
                f"mvviz: {own} cannot be written ({why}): results and caches of this scene "
                f"go to {fallback}",
                file=sys.stderr,
                flush=True,
            )
        _OWN_CACHE[key] = fallback
    fallback = _OWN_CACHE[key]
    return root / CACHE_DIR if fallback is None else fallback


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


class SceneFormatError(ValueError):
    """Bad input: names the file, the field and what was expected."""

    def __init__(self, path: str | os.PathLike, field: str | None, message: str) -> None:
        self.path = str(path)
        self.field = field
        where = f"{self.path}: field '{field}'" if field else self.path
        super().__init__(f"{where}: {message}")


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` exists (another user's counts: it cannot be signalled,
    but it is there)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # someone else's live process
    return True


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            p.unlink()


def recover(path: str | os.PathLike) -> None:
    """Finish what dead writers of ``path`` left: remove their temporary files and
    complete (or roll back) an interrupted directory replacement (see the module
    docstring). Leftovers of live processes are not touched."""
    path = Path(path)
    if not path.parent.is_dir():
        return
    pattern = re.compile(r"^\." + re.escape(path.name) + r"\.(?:(\d+)\..*\.tmp|(old|new)-(\d+))$")
    stale: dict[str, list[Path]] = {"tmp": [], "old": [], "new": []}
    for entry in path.parent.iterdir():
        m = pattern.match(entry.name)
        if m is None:
            continue
        pid = int(m.group(1) or m.group(3))
        if not process_alive(pid):
            stale[m.group(2) or "tmp"].append(entry)
    try:
        for p in stale["tmp"]:
            _remove(p)
        for p in stale["new"]:  # complete: only ever renamed from a finished temporary
            if not path.exists():
                os.replace(p, path)
            else:
                _remove(p)  # the kill came before the old one moved away: the old one stays
        for p in stale["old"]:
            if not path.exists():
                os.replace(p, path)  # no new one to complete with: roll back
            else:
                _remove(p)
    except OSError as exc:  # a read-only folder or mount: left as it is, read as it is
        if exc.errno not in (errno.EACCES, errno.EPERM, errno.EROFS):
            raise


def read_text_lines(path: str | os.PathLike) -> list[str]:
    """A UTF-8 text file's lines; a missing or binary file is a :class:`SceneFormatError`
    naming it (the line-based importers: TRC, BVH)."""
    path = Path(path)
    if not path.is_file():
        raise SceneFormatError(path, None, "file not found")
    try:
        return path.read_text(encoding="utf-8", errors="strict").splitlines()
    except UnicodeDecodeError as exc:
        raise SceneFormatError(path, None, f"not a text file ({exc})") from None


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb") -> Iterator:
    """Open a temporary file beside ``path``; it replaces ``path`` only if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    recover(path)
    prefix = f".{path.name}.{os.getpid()}."
    fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual file mode
        os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if exc.filename is None:  # a full disk or a file-size limit: name what was written
            raise OSError(exc.errno, f"{exc.strerror}: writing {path}") from exc
        raise
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def save_npz_atomic(path: str | os.PathLike, **arrays: np.ndarray) -> None:
    """``np.savez_compressed`` through :func:`atomic_write`."""
    with atomic_write(path) as fh:
        np.savez_compressed(fh, **arrays)


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a fresh temporary directory that becomes ``path`` only if the block succeeds.

    An existing non-empty ``path`` is an error unless ``overwrite``; then it is
    replaced as a whole after the new one is complete.
    """
    path = Path(path)
    recover(path)
    if path.exists() and any(path.iterdir()) and not overwrite:
        raise FileExistsError(f"{path} exists and is not empty (pass overwrite to replace it)")
    path.parent.mkdir(parents=True, exist_ok=True)
    prefix = f".{path.name}.{os.getpid()}."
    tmp = Path(tempfile.mkdtemp(prefix=prefix, suffix=".tmp", dir=path.parent))
    old = path.with_name(f".{path.name}.old-{os.getpid()}")
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes 0700
        if path.exists():
            new = path.with_name(f".{path.name}.new-{os.getpid()}")
            os.replace(tmp, new)  # complete, under a name recover() knows
            tmp = new
            os.replace(path, old)
            os.replace(new, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        if old.exists() and not path.exists():
            os.replace(old, path)  # failed between the renames: put the old one back
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def require_file(path: Path) -> None:
    """A SceneFormatError unless ``path`` is a file (a directory is named as one)."""
    if not path.is_file():
        what = "is a directory, expected a file" if path.is_dir() else "file not found"
        raise SceneFormatError(path, None, what)


def load_toml(path: str | os.PathLike) -> dict:
    """A TOML file's tables (calibrations, board descriptions); a missing file or bad TOML
    is a SceneFormatError naming the file."""
    path = Path(path)
    require_file(path)
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SceneFormatError(path, None, f"not valid TOML ({exc})") from exc


def load_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """All arrays of an npz file, with a clear error if it is missing or unreadable."""
    path = Path(path)
    if not path.is_file():
        raise SceneFormatError(path, None, "file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as exc:  # zipfile/pickle/format errors all mean "not a valid npz"
        raise SceneFormatError(path, None, f"not a readable .npz file ({exc})") from exc
