"""The ``occplug`` command line.

Each sub-command lives in its own module exposing ``add_parsers(subparsers)``; :data:`COMMANDS`
lists them in help order.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence

from occplug.errors import UserError
from occplug.registry import ComponentClashError, UnknownComponentError

from .errors import UsageError

__all__ = ["COMMANDS", "add_config_args", "build_parser", "main"]

#: Modules under ``occplug.cli`` that add sub-commands, in help order.
COMMANDS = (
    "run",
    "plugins_cmd",
    "config_cmd",
    "data_cmd",
    "eval_cmd",
    "viz_cmd",
    "export_cmd",
    "bench_cmd",
    "completion_cmd",
)


def add_config_args(p: argparse.ArgumentParser) -> None:
    """``-c CONFIG`` (repeatable) and trailing ``key=value`` overrides."""
    p.add_argument(
        "-c",
        "--config",
        action="append",
        default=[],
        metavar="REF",
        help="config file or reference (e.g. configs/baseline.yaml, queryocc/base); repeat to merge in order",
    )
    p.add_argument("overrides", nargs="*", metavar="key=value", help="dotlist overrides applied last (~key deletes)")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every sub-command."""
    parser = argparse.ArgumentParser(
        prog="occplug", description="3D semantic occupancy prediction, one plugin at a time."
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"occplug.cli.{name}").add_parsers(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``occplug`` console script; returns the exit code.

    User mistakes (config errors, unknown components, bad paths) print one ``error:`` line and
    return 2.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        result = args.func(args)
        sys.stdout.flush()  # inside the try: a closed pipe shows here, not at interpreter exit
    except BrokenPipeError:
        # the reader went away (`| head`, `| grep -q`): stop quietly with SIGPIPE's status, as Unix tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except (UserError, UsageError, UnknownComponentError, ComponentClashError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return int(result or 0)
