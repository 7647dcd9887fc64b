"""``occplug fit | validate | test | predict``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import yaml

from occplug import runner

from .errors import UsageError


def _print_metrics(results: dict[str, float]) -> None:
    headline = {k: v for k, v in results.items() if not k.startswith("IoU_")}
    print("metrics: " + ", ".join(f"{k}={v:.2f}" for k, v in headline.items()))


def cmd_fit(args: argparse.Namespace) -> int:
    try:
        if args.resume:
            run_dir = Path(args.resume)
            saved_path = run_dir / "config.yaml"
            if not saved_path.is_file():
                raise UsageError(f"--resume {run_dir}: no config.yaml there (not an occplug run directory)")
            saved = yaml.safe_load(saved_path.read_text())
            cfg = runner.load_config(args.config, args.overrides, saved=saved)
        else:
            if not args.config:
                raise UsageError("fit needs -c CONFIG (or --resume RUN_DIR)")
            cfg = runner.load_config(args.config, args.overrides)
            run_dir = Path(args.run_dir) if args.run_dir else runner.default_run_dir(args.config)
        results = runner.fit(cfg, run_dir, resume=bool(args.resume))
    except runner.RunError as exc:
        raise UsageError(str(exc)) from None
    _print_metrics(results)
    print(f"run directory: {run_dir}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    try:
        cfg = runner.resolve_run_config(args.config, args.overrides, Path(args.ckpt))
        results, tables = runner.evaluate(cfg, Path(args.ckpt), stage=args.stage)
    except runner.RunError as exc:
        raise UsageError(str(exc)) from None
    for table in tables.values():
        if table:
            print(table)
    _print_metrics(results)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")
    return 0


def cmd_predict(args: argparse.Namespace) -> int:
    try:
        cfg = runner.resolve_run_config(args.config, args.overrides, Path(args.ckpt))
        count = runner.predict(cfg, Path(args.ckpt), Path(args.out))
    except runner.RunError as exc:
        raise UsageError(str(exc)) from None
    print(f"wrote {count} predictions to {args.out}")
    return 0
