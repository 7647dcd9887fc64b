"""The ``occplug`` command line: ``fit | validate | test | predict | plugins | config | data``."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from occplug.config.errors import ConfigError
from occplug.registry import ComponentClashError, UnknownComponentError

from .errors import UsageError

__all__ = ["build_parser", "main"]


def _add_config_args(p: argparse.ArgumentParser, required: bool = True) -> None:
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
    from . import config_cmd, data_cmd, plugins_cmd, run

    parser = argparse.ArgumentParser(prog="occplug", description="3D semantic occupancy prediction, one plugin at a time.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    fit = sub.add_parser("fit", help="train a model; writes a run directory")
    _add_config_args(fit)
    fit.add_argument("--run-dir", metavar="DIR", help="where to write the run (default: runs/<time>-<config name>)")
    fit.add_argument("--resume", metavar="DIR", help="continue the run in DIR from its last checkpoint")
    fit.set_defaults(func=run.cmd_fit)

    for name, helptext in (("validate", "evaluate on the validation split"), ("test", "evaluate on the test split")):
        p = sub.add_parser(name, help=helptext)
        _add_config_args(p)
        p.add_argument("--ckpt", required=True, metavar="FILE", help="checkpoint to evaluate")
        p.add_argument("--json", metavar="FILE", help="also write the metrics to this JSON file")
        p.set_defaults(func=run.cmd_evaluate, stage=name)

    pred = sub.add_parser("predict", help="write one <token>.npz (key 'pred') per sample")
    _add_config_args(pred)
    pred.add_argument("--ckpt", required=True, metavar="FILE")
    pred.add_argument("--out", required=True, metavar="DIR", help="output folder for the .npz files")
    pred.set_defaults(func=run.cmd_predict)

    plugins = sub.add_parser("plugins", help="list installed plugins and their components")
    plugins.add_argument("--json", action="store_true", help="print JSON")
    plugins.add_argument("--kind", help="only components of this kind")
    plugins.set_defaults(func=plugins_cmd.cmd_plugins)

    config = sub.add_parser("config", help="inspect configs")
    config_sub = config.add_subparsers(dest="config_command", required=True, metavar="ACTION")
    show = config_sub.add_parser("show", help="print the composed, resolved config")
    _add_config_args(show)
    show.add_argument("--explain", metavar="KEY", help="say which file or override set KEY")
    show.add_argument("--no-validate", action="store_true", help="print without validating")
    show.set_defaults(func=config_cmd.cmd_show)

    data = sub.add_parser("data", help="data sets")
    data_sub = data.add_subparsers(dest="data_command", required=True, metavar="ACTION")
    synth = data_sub.add_parser("synth", help="write the synthetic world to disk")
    synth.add_argument("--out", required=True, metavar="DIR")
    synth.add_argument("--preset", default="default", help="world preset (tiny, default, occ3d)")
    synth.add_argument("--splits", nargs="+", default=["train", "val", "test"], help="splits to write")
    synth.add_argument("knobs", nargs="*", metavar="key=value", help="synthetic data-module arguments, e.g. seed=3")
    synth.set_defaults(func=data_cmd.cmd_synth)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``occplug`` console script; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        result = args.func(args)
    except (ConfigError, UsageError, UnknownComponentError, ComponentClashError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return int(result or 0)

