"""Notes on frames (:class:`Note`), kept as JSON beside the results:
``SCENE/.mvviz/notes.json``."""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from datetime import datetime
from pathlib import Path

from pipeline.core.files import SceneFormatError, atomic_write, scene_cache_dir

NOTES_VERSION = 1
NOTES_FILE = "notes.json"  # in the scene's cache folder (scene_cache_dir)


@dataclass(frozen=True)
class Note:
    """A researcher's note on a frame; ``created`` is ISO 8601 local time with offset."""

    frame: int
    text: str
    created: str


def new_note(frame: int, text: str) -> Note:
    return Note(int(frame), str(text), datetime.now().astimezone().isoformat(timespec="seconds"))


def notes_path(scene_root: str | os.PathLike) -> Path:
    """Where a scene's notes live: ``SCENE/.mvviz/notes.json`` (beside the results; in the
    user's cache for a scene folder that cannot be written: :func:`scene_cache_dir`)."""
    return scene_cache_dir(scene_root) / NOTES_FILE


def load_notes(path: str | os.PathLike) -> list[Note]:
    """The notes in ``path`` (none if it does not exist). A file that is not valid notes
    JSON raises :class:`~pipeline.core.files.SceneFormatError` naming it and the bad field."""
    path = Path(path)
    if not path.exists():
        return []
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SceneFormatError(path, None, f"not a readable notes file ({exc})") from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("notes"), list):
        raise SceneFormatError(path, "notes", "expected an object with a list 'notes'")
    if doc.get("version") != NOTES_VERSION:
        raise SceneFormatError(path, "version", f"expected {NOTES_VERSION}")
    notes = []
    for i, n in enumerate(doc["notes"]):
        where = f"notes[{i}]"
        if not isinstance(n, dict):
            raise SceneFormatError(path, where, "expected an object")
        frame, text, created = n.get("frame"), n.get("text"), n.get("created")
        if not isinstance(frame, int) or isinstance(frame, bool) or frame < 0:
            raise SceneFormatError(path, f"{where}.frame", f"expected a frame >= 0, got {frame!r}")
        if not isinstance(text, str):
            raise SceneFormatError(path, f"{where}.text", "expected a string")
        if not isinstance(created, str):
            raise SceneFormatError(path, f"{where}.created", "expected an ISO time string")
        try:
            datetime.fromisoformat(created)
        except ValueError:
            raise SceneFormatError(
                path, f"{where}.created", f"not an ISO time: {created!r}"
            ) from None
        notes.append(Note(frame, text, created))
    return notes


def save_notes(path: str | os.PathLike, notes: list[Note]) -> None:
    """Write ``notes`` to ``path`` atomically (a failed write leaves the old file)."""
    doc = {"version": NOTES_VERSION, "notes": [asdict(n) for n in notes]}
    with atomic_write(path, "w") as fh:
        json.dump(doc, fh, indent=2, ensure_ascii=False)
        fh.write("\n")
