"""What the benchmark scripts share: a free local port and writing their figures."""

from __future__ import annotations

import json
import socket
from pathlib import Path

from pipeline.core.files import atomic_write


def free_port() -> int:
    """A TCP port on 127.0.0.1 nobody listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_json(path: Path, figures: dict) -> None:
    """``figures`` as indented JSON at ``path``, written atomically."""
    with atomic_write(path, "w") as fh:
        fh.write(json.dumps(figures, indent=1) + "\n")
