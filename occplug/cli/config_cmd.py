"""``occplug config show | validate``."""

from __future__ import annotations

import argparse
import json

from occplug.config import compose, validate
from occplug.config.defaults import annotated_yaml
from occplug.config.phases import PHASE_KEYS, phase_specs
from occplug.config.yamlio import dump_yaml
from occplug.plugins import get_registry

from . import add_config_args
from .errors import UsageError
from .paths import config_refs


def add_parsers(sub: argparse._SubParsersAction) -> None:
    config = sub.add_parser("config", help="inspect configs")
    actions = config.add_subparsers(dest="config_command", required=True, metavar="ACTION")
    show = actions.add_parser("show", help="print the composed, resolved config")
    add_config_args(show)
    show.add_argument("--explain", metavar="KEY", help="say which file or override set KEY")
    show.add_argument("--no-validate", action="store_true", help="print without validating")
    show.add_argument(
        "--defaults",
        action="store_true",
        help="also print every component argument the config leaves out, each with its type, rule and default",
    )
    show.set_defaults(func=cmd_show)
    check = actions.add_parser(
        "validate", help="check the composed config (components, arguments, query heads); builds nothing"
    )
    add_config_args(check)
    check.set_defaults(func=cmd_validate)


def cmd_show(args: argparse.Namespace) -> int:
    if not args.config:
        raise UsageError("config show needs at least one -c CONFIG")
    config_refs(args.config)
    composed = compose(args.config, args.overrides)
    resolved = composed.resolved()
    if not args.no_validate:
        validate(resolved, get_registry())
    if args.explain:
        key = args.explain
        hits = {k: v for k, v in composed.sources.items() if k == key or k.startswith(key + ".")}
        if not hits:
            raise UsageError(f"--explain {key}: no such key in the composed config")
        for k, origin in sorted(hits.items()):
            print(f"{k}: set by {origin}")
        return 0
    registry = get_registry()
    show = (lambda cfg: annotated_yaml(cfg, registry)) if args.defaults else dump_yaml
    print(show(resolved), end="")
    specs = phase_specs(resolved)
    for i, spec in enumerate(specs, 1):  # each phase's whole config, as fit runs it
        own = {k: spec.overlay[k] for k in PHASE_KEYS if k in spec.overlay}
        settings = f" ({json.dumps(own)})" if own else ""
        print(f"---\n# phase {i}/{len(specs)}: {spec.name}{settings}")
        print(show(spec.config), end="")
    return 0


def cmd_validate(args: argparse.Namespace) -> int:
    if not args.config:
        raise UsageError("config validate needs at least one -c CONFIG")
    config_refs(args.config)
    validate(compose(args.config, args.overrides).resolved(), get_registry())
    print(f"ok: {' + '.join(args.config)}")
    return 0
