"""``occplug bench RUN_OR_CONFIG...``: one table comparing models on this machine (see :mod:`occplug.run.bench`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import paths as check
from .errors import UsageError


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench",
        help="measure models side by side: parameters, latency, memory, training step, recorded accuracy",
        description="Each model is measured in its own process, the repeats of all models interleaved. "
        "A run directory adds the accuracy its metrics.json recorded; a config has none (shown as —).",
    )
    p.add_argument("targets", nargs="+", metavar="RUN_OR_CONFIG", help="run directories and/or configs")
    fmt = p.add_mutually_exclusive_group()
    fmt.add_argument("--csv", action="store_true", help="print CSV instead of a Markdown table")
    fmt.add_argument("--json", action="store_true", help="print JSON instead of a Markdown table")
    p.add_argument("--repeats", type=int, default=10, help="timed inference repeats per model (default 10)")
    p.add_argument("--warmup", type=int, default=3, help="untimed repeats first (default 3)")
    p.add_argument(
        "--train-repeats", type=int, default=5, help="timed training steps per model (default 5; 0: inference only)"
    )
    p.add_argument("--batch-size", type=int, default=1, help="frames per inference and training batch (default 1)")
    p.add_argument("--device", default="auto", help="auto (CUDA when present), cpu or cuda (default auto)")
    p.add_argument("--preset", help="data.preset for configs, e.g. tiny (run directories keep their data)")
    p.add_argument("-o", "--out", metavar="FILE", help="also write the table to FILE")
    p.set_defaults(func=cmd_bench)


def cmd_bench(args: argparse.Namespace) -> int:
    from occplug.run.bench import BenchSettings, resolve_target, run_bench

    for flag in ("repeats", "batch_size"):
        if getattr(args, flag) < 1:
            raise UsageError(f"--{flag.replace('_', '-')}: expected an int >= 1, got {getattr(args, flag)}")
    if args.train_repeats < 0:
        raise UsageError(f"--train-repeats: expected an int >= 0 (0: inference only), got {args.train_repeats}")
    if args.warmup < 0:
        raise UsageError(f"--warmup: expected an int >= 0, got {args.warmup}")
    if args.out:
        check.output_file("--out", args.out)  # before measuring: a bad path must not cost the whole run
    settings = BenchSettings(
        repeats=args.repeats,
        warmup=args.warmup,
        train_repeats=args.train_repeats,
        batch_size=args.batch_size,
        device=args.device,
        preset=args.preset,
    )
    targets = [resolve_target(ref, settings) for ref in args.targets]  # every input checked before measuring
    report = run_bench(targets, settings, progress=lambda msg: print(msg, file=sys.stderr))
    text = report.to_json() if args.json else report.to_csv() if args.csv else report.to_markdown()
    if args.out:
        from occplug.run.runner import write_text_atomic

        try:
            write_text_atomic(Path(args.out), text)  # a reader never sees half a table
        except OSError as exc:
            raise UsageError(f"--out {args.out}: cannot write ({exc.strerror})") from None
    sys.stdout.write(text)
    return 0
