"""The ``mvviz`` command line: one subcommand per job, each registered by its module.

One module per subcommand group (``convert``, ``calibrate``, ``reference``, ``synth`` /
``synth_mocap``, ``detect``, ``run`` (also ``eval``), ``batch``, ``export_rrd``, ``export_formats``,
``diagnose``, ``compare``, ``view``, ``prior``). The command line is the top of the
import graph: it may import everything; nothing in :mod:`mvviz` outside this package
imports it (``app.py`` at the repository root does).

Each ``register(subparsers)`` adds a parser whose ``func(args) -> int`` runs the job.
Errors: bad input (:class:`~pipeline.core.files.SceneFormatError`, and OS errors such as a
missing file or a full disk) is one line on stderr and exit code 2; anything else is a
bug, reported in one line with exit code 1 (``--debug`` prints its traceback).
"""

from __future__ import annotations

import argparse
import atexit
import importlib
import os
import sys
import threading
import traceback
from collections.abc import Callable

from pipeline.core.files import SceneFormatError

COMMAND_MODULES = {
    "convert": "convert", "calibrate": "calibrate", "add-reference": "reference",
    "synth": "synth", "detect": "detect", "run": "run", "eval": "run", "batch": "batch",
    "export-rrd": "export_rrd",
    "export": "export_formats", "diagnose": "diagnose", "compare": "compare", "view": "view",
    "train-prior": "prior",
}  # fmt: skip
"""Each subcommand's module, in --help's order. A command line naming one imports only
that module: every module together imports ray, torch and matplotlib (~12 s here), which
``mvviz view`` and ``mvviz export-rrd`` would otherwise pay before doing anything."""


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser of ``argv``'s subcommand (all of them when it names none, e.g. --help)."""
    words = [a for a in (sys.argv[1:] if argv is None else argv) if not a.startswith("-")]
    named = words[0] if words and words[0] in COMMAND_MODULES else None
    wanted = [COMMAND_MODULES[named]] if named else list(dict.fromkeys(COMMAND_MODULES.values()))
    parser = argparse.ArgumentParser(
        prog="mvviz",
        description="Multi-view, multi-person 3D pose and SMPL reconstruction, and its debugger.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in wanted:
        importlib.import_module(f"mvviz.cli.{name}").register(sub)
    add_debug_option(parser)
    for p in sub.choices.values():
        add_debug_option(p, default=argparse.SUPPRESS)  # also after the subcommand
    return parser


INPUT_ERRORS = (SceneFormatError, OSError)
"""What bad input raises: exit code 2 and one line, never a traceback."""


def at_least(low: int) -> Callable[[str], int]:
    """An argparse ``type``: an integer >= ``low`` (a count), else a usage error naming
    the option and the value (exit 2, nothing run), not a failure deep in a stage."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {value}")
        return value

    return parse


def add_debug_option(parser: argparse.ArgumentParser, default=False) -> None:
    parser.add_argument(
        "--debug", action="store_true", default=default,
        help="print the traceback of an unexpected error",
    )  # fmt: skip


def run_command(prog: str, func: Callable[[argparse.Namespace], int | None], args) -> int:
    """``func(args)``'s exit code; input errors -> 2, other exceptions -> 1 (see above)."""
    try:
        return int(func(args) or 0)
    except INPUT_ERRORS as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        if getattr(args, "debug", False):
            traceback.print_exc()
        hint = "" if getattr(args, "debug", False) else " (run with --debug for the traceback)"
        print(f"{prog}: internal error: {type(exc).__name__}: {exc}{hint}", file=sys.stderr)
        return 1


def main(argv: list[str] | None = None) -> int:
    args = build_parser(argv).parse_args(argv)
    return run_command(f"mvviz {args.command}", args.func, args)


def entry() -> None:
    """The ``mvviz`` script and ``python -m mvviz.cli``: :func:`main`, then
    :func:`exit_now` with its code."""
    exit_now(main())


def exit_now(code: int) -> None:
    """End the process with ``code`` once the command's work is done: the exit functions
    run (Ray's shutdown, logging's flush, temporary directories' removal) and the
    standard streams are flushed, but not the interpreter's teardown of every module
    and object, which takes 0.3-0.6 s here after torch, Ray or matplotlib were imported
    (``mvviz run`` 0.6 s, ``mvviz batch``'s driver 0.35 s of its fixed cost).

    Where a non-daemon thread still runs, the normal exit, which waits for it."""
    main_thread = threading.main_thread()  # enumerate() lists the live threads only
    waiting = any(not t.daemon for t in threading.enumerate() if t is not main_thread)
    run_exit_functions = getattr(atexit, "_run_exitfuncs", None)  # CPython's own hook
    if waiting or run_exit_functions is None:
        sys.exit(code)
    run_exit_functions()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # closed, or its reader has gone
            pass
    os._exit(code)
