"""The ``mvviz`` command line: one subcommand per job, each registered by its module.

Each ``register(subparsers)`` adds a parser whose ``func(args) -> int`` runs the job.
"""

from __future__ import annotations

import argparse
import sys

from pipeline.files import SceneFormatError


def build_parser() -> argparse.ArgumentParser:
    from mvviz import (  # noqa: PLC0415  (keeps --help fast)
        cli_convert,
        cli_detect,
        cli_export,
        cli_prior,
        cli_reference,
        cli_run,
        cli_synth,
        cli_view,
    )

    parser = argparse.ArgumentParser(
        prog="mvviz",
        description="Multi-view, multi-person 3D pose and SMPL reconstruction, and its debugger.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in (
        cli_convert,
        cli_reference,
        cli_synth,
        cli_detect,
        cli_run,
        cli_export,
        cli_view,
        cli_prior,
    ):
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (SceneFormatError, FileExistsError, FileNotFoundError) as exc:
        print(f"mvviz {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
