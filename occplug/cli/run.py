"""``occplug fit | validate | test | predict``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from occplug.plugins import broken_plugins_warning
from occplug.run import runner
from occplug.run.phases import fit_phases

from . import add_config_args
from . import paths as check
from .errors import UsageError


def add_parsers(sub: argparse._SubParsersAction) -> None:
    fit = sub.add_parser("fit", help="train a model; writes a run directory")
    add_config_args(fit)
    fit.add_argument("--run-dir", metavar="DIR", help="where to write the run (default: runs/<time>-<config name>)")
    fit.add_argument("--resume", metavar="DIR", help="continue the run in DIR from its last checkpoint")
    fit.set_defaults(func=cmd_fit)
    for name, helptext in (("validate", "evaluate on the validation split"), ("test", "evaluate on the test split")):
        p = sub.add_parser(name, help=helptext)
        add_config_args(p)
        p.add_argument("--ckpt", required=True, metavar="FILE", help="checkpoint to evaluate")
        p.add_argument("--json", metavar="FILE", help="also write the metrics to this JSON file")
        p.set_defaults(func=cmd_evaluate, stage=name)
    pred = sub.add_parser("predict", help="write one <token>.npz (key 'pred') per sample")
    add_config_args(pred)
    pred.add_argument("--ckpt", required=True, metavar="FILE")
    pred.add_argument("--out", required=True, metavar="DIR", help="output folder for the .npz files")
    pred.set_defaults(func=cmd_predict)


def _print_metrics(results: dict[str, float]) -> None:
    headline = {k: v for k, v in results.items() if not k.split("/")[-1].startswith("IoU_")}
    print("metrics: " + ", ".join(f"{k}={v:.2f}" for k, v in headline.items()))


def cmd_fit(args: argparse.Namespace) -> int:
    warning = broken_plugins_warning()
    if warning and runner.is_rank_zero():
        print(warning, file=sys.stderr)
    check.config_refs(args.config)
    if args.resume:
        check.input_dir("--resume", args.resume)
    elif args.run_dir:
        check.output_dir("--run-dir", args.run_dir, make_parents=True)
    try:
        if args.resume:
            run_dir = Path(args.resume)
            saved_path = run_dir / "config.yaml"
            if not saved_path.is_file():
                raise UsageError(f"--resume {run_dir}: no config.yaml there (not an occplug run directory)")
            saved = runner.read_run_config(saved_path)
            cfg = runner.load_config(args.config, args.overrides, saved=saved)
        else:
            if not args.config:
                raise UsageError("fit needs -c CONFIG (or --resume RUN_DIR)")
            cfg = runner.load_config(args.config, args.overrides)
            run_dir = Path(args.run_dir) if args.run_dir else runner.default_run_dir(args.config)
        fit = fit_phases if cfg.get("phases") is not None else runner.fit
        results = fit(cfg, run_dir, resume=bool(args.resume))
    except runner.RunError as exc:
        raise UsageError(str(exc)) from None
    except runner.RunInterrupted as stop:  # SIGTERM / SIGINT: a checkpoint, then a scheduler-visible failure
        print(f"interrupted: {stop.message}; continue with: occplug fit --resume {run_dir}", file=sys.stderr)
        return stop.exit_code
    if runner.is_rank_zero():  # DDP: every rank runs this command; one reports
        _print_metrics(results)
        print(f"run directory: {run_dir}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    check.config_refs(args.config)
    check.input_file("--ckpt", args.ckpt)
    if args.json:
        check.output_file("--json", args.json)
    try:
        cfg = runner.resolve_run_config(args.config, args.overrides, Path(args.ckpt))
        found = runner.evaluate(cfg, Path(args.ckpt), stage=args.stage)
    except runner.RunError as exc:
        raise UsageError(str(exc)) from None
    if not runner.is_rank_zero():  # DDP: every rank runs this command; one reports
        return 0
    runner.print_tables(found.tables, found.masks)
    _print_metrics(found.results)
    if args.json:
        runner.write_json(Path(args.json), {**found.results, **found.masks})
    return 0


def cmd_predict(args: argparse.Namespace) -> int:
    check.config_refs(args.config)
    check.input_file("--ckpt", args.ckpt)
    check.output_dir("--out", args.out)
    try:
        cfg = runner.resolve_run_config(args.config, args.overrides, Path(args.ckpt))
        count = runner.predict(cfg, Path(args.ckpt), Path(args.out))
    except runner.RunError as exc:
        raise UsageError(str(exc)) from None
    if runner.is_rank_zero():
        print(f"wrote {count} predictions to {args.out}")
    return 0
