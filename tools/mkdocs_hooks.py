"""MkDocs hooks: pages whose content comes from the code, so they cannot drift from it.

``<!-- mvviz-cli -->`` in a page becomes the help of every ``mvviz`` subcommand and of
``python app.py``, generated from their argparse definitions at build time.
"""

from __future__ import annotations

import argparse
import os

CLI_MARKER = "<!-- mvviz-cli -->"


def _help_text(parser: argparse.ArgumentParser) -> str:
    # A fixed width: the page is the same whatever terminal built it.
    os.environ["COLUMNS"] = "96"
    return parser.format_help().rstrip()


def cli_reference() -> str:
    """Markdown: one section per command, its ``--help`` verbatim."""
    import app
    from mvviz.cli import COMMAND_MODULES, build_parser

    parser = build_parser([])
    subparsers = next(
        a for a in parser._actions if isinstance(a, argparse._SubParsersAction)
    ).choices
    parts = ["## `python app.py`", "", "```text", _help_text(app.build_parser()), "```", ""]
    for name in COMMAND_MODULES:
        parts += [f"## `mvviz {name}`", "", "```text", _help_text(subparsers[name]), "```", ""]
    return "\n".join(parts)


def on_page_markdown(markdown: str, page, config, files) -> str:  # noqa: ARG001
    if CLI_MARKER in markdown:
        markdown = markdown.replace(CLI_MARKER, cli_reference())
    return markdown
