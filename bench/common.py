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


BENCH_PAGES = Path(__file__).resolve().parents[1] / "docs" / "benchmarks"
"""Where ``--docs`` puts each benchmark's section of the documentation's Benchmarks page."""


def machine_line() -> str:
    """The machine a figure was measured on: CPU model, cores, memory, load, Python."""
    import os
    import platform

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        mem_gb = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
        mem = f", {mem_gb:.0f} GiB"
    except (ValueError, OSError, AttributeError):
        mem = ""
    load = f", load {os.getloadavg()[0]:.1f}" if hasattr(os, "getloadavg") else ""
    return f"{cpu}, {os.cpu_count()} cores{mem}{load}; Python {platform.python_version()}"


def markdown_table(header: list[str], rows: list[list]) -> str:
    """A Markdown table; numbers as given (format them before)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def publish(name: str, title: str, body: str, *, argv: list[str] | None = None) -> Path:
    """Write this run's figures as ``docs/benchmarks/<name>.md``, the section of the
    Benchmarks page that the documentation includes: title, the command and the machine
    of the run, then ``body`` (Markdown). Written atomically."""
    import sys

    args = sys.argv[1:] if argv is None else argv
    command = " ".join(["python", f"bench/{name}.py", *[a for a in args if a != "--docs"]])
    text = (
        f"## {title}\n\n`{command}`\n\n*Measured on {machine_line()}.*\n\n"
        f"{body.strip()}\n"
    )
    path = BENCH_PAGES / f"{name}.md"
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "w") as fh:
        fh.write(text)
    print(f"wrote {path}")
    return path
