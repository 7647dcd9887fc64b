"""``occplug export``: a checkpoint's inference path as a torch.export archive or an ONNX model, with a parity report."""

from __future__ import annotations

import argparse
from pathlib import Path

from occplug import runner

from .errors import UsageError


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export",
        help="export a checkpoint's inference path (torch.export or ONNX) and check it against the eager model",
        description="Export images + calibration -> class ids and logits on the evaluation grid, from the "
        "checkpoint alone; write <out>.parity.json beside the artefact and print it in one line.",
    )
    p.add_argument("--ckpt", required=True, metavar="FILE", help="checkpoint to export (its config is used)")
    p.add_argument("--format", required=True, choices=("torch_export", "onnx"), help="artefact format")
    p.add_argument("--out", required=True, metavar="FILE", help="artefact file (e.g. model.pt2, model.onnx)")
    p.add_argument(
        "--samples", type=int, default=4, metavar="N",
        help="validation frames to check parity on; each also with perturbed calibration (default: 4)",
    )
    p.set_defaults(func=cmd_export)


def cmd_export(args: argparse.Namespace) -> int:
    from occplug.export import export_checkpoint, one_line

    try:
        report = export_checkpoint(Path(args.ckpt), args.format, Path(args.out), samples=args.samples)
    except runner.RunError as exc:
        raise UsageError(str(exc)) from None
    print(one_line(report))
    if not report["passed"]:
        print(f"error: the exported model disagrees with the eager one (see {report['artefact']}.parity.json)")
        return 1
    return 0
