"""``occplug plugins``: what is installed, what it registers, what failed to load."""

from __future__ import annotations

import argparse
import json

from occplug.config.defaults import Argument, arguments
from occplug.kinds import KINDS
from occplug.plugins import get_registry, plugin_reports

from .errors import UsageError


def add_parsers(sub: argparse._SubParsersAction) -> None:
    plugins = sub.add_parser("plugins", help="list installed plugins and their components")
    plugins.add_argument("--json", action="store_true", help="print JSON")
    plugins.add_argument(
        "--kind", help="only components of this kind, each with its constructor arguments (name, type, rule, default)"
    )
    plugins.set_defaults(func=cmd_plugins)


def cmd_plugins(args: argparse.Namespace) -> int:
    if args.kind is not None and args.kind not in KINDS:
        raise UsageError(f"--kind {args.kind}: unknown kind; kinds are: {', '.join(KINDS)}")
    registry = get_registry()
    reports = plugin_reports()
    if args.json:
        out = []
        for r in reports:
            d = r.to_dict()
            if args.kind:
                d["components"] = {k: v for k, v in d["components"].items() if k == args.kind}
            # where each component's code is, so a config's `type:` reaches it in one step
            d["sources"] = {k: {n: registry.get(k, n).source for n in names} for k, names in d["components"].items()}
            if args.kind:  # what a config node of each component may set
                d["arguments"] = {
                    k: {n: [_argument_json(a) for a in arguments(registry.get(k, n).factory, k)] for n in names}
                    for k, names in d["components"].items()
                }
            out.append(d)
        print(json.dumps(out, indent=2))
        return 0
    entries = [registry.get(k, n) for r in reports for k, ns in r.components.items() for n in ns]
    name_width = max((len(e.name) for e in entries), default=0)
    width = max((len(e.source) for e in entries), default=0)
    for r in reports:
        version = f" {r.version}" if r.version else ""
        dist = f" [{r.distribution}{version}]" if r.distribution else ""
        print(f"{r.name}{dist}")
        if r.error:
            print(f"  ERROR: {r.error}")
        for kind in KINDS:
            if args.kind and kind != args.kind:
                continue
            for name in r.components.get(kind, []):
                entry = registry.get(kind, name)
                print(f"  {kind:<15} {name:<{name_width}} {entry.source:<{width}}  {entry.summary}")
                if args.kind:
                    for arg in arguments(entry.factory, kind):
                        print(f"      {arg.name}: {arg.describe()}")
    return 0


def _argument_json(arg: Argument) -> dict[str, object]:
    return {
        "name": arg.name,
        "type": arg.type,
        "rule": arg.rule or None,
        "required": arg.required,
        "given": arg.given,
        "default": arg.default if arg.representable else None,
        "default_is_plain_data": arg.representable or arg.required,
    }
