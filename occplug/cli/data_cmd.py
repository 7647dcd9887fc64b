"""``occplug data synth``: write the synthetic world to disk."""

from __future__ import annotations

import argparse
from pathlib import Path

import yaml

from occplug.config import ConfigError
from occplug.config.validate import _Validator
from occplug.plugins import get_registry

from .errors import UsageError


def add_parsers(sub: argparse._SubParsersAction) -> None:
    data = sub.add_parser("data", help="data sets")
    actions = data.add_subparsers(dest="data_command", required=True, metavar="ACTION")
    synth = actions.add_parser("synth", help="write the synthetic world to disk")
    synth.add_argument("--out", required=True, metavar="DIR")
    synth.add_argument("--preset", default="default", help="world preset (tiny, default, occ3d)")
    synth.add_argument("--splits", nargs="+", default=["train", "val", "test"], help="splits to write")
    synth.add_argument("knobs", nargs="*", metavar="key=value", help="synthetic data-module arguments, e.g. seed=3")
    synth.set_defaults(func=cmd_synth)


def cmd_synth(args: argparse.Namespace) -> int:
    from occplug.data.synthetic import write_dataset

    node: dict = {"type": "synthetic", "preset": args.preset}
    for item in args.knobs:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"'{item}': expected key=value (a synthetic data-module argument)")
        node[key] = yaml.safe_load(raw) if raw.strip() else None
    registry = get_registry()
    _Validator(registry).node(node, "data", "data")
    out = Path(args.out)
    if out.exists() and any(out.iterdir()):
        raise UsageError(f"--out {out}: the folder exists and is not empty")
    try:
        dm = registry.build("data", node)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    count = write_dataset(dm.world_config, out, splits=tuple(args.splits), progress=True)
    print(f"wrote {count} frames to {out}")
    return 0
