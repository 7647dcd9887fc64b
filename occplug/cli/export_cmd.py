"""``occplug export``: a checkpoint's inference path as a torch.export archive or an ONNX model, with a parity report."""

from __future__ import annotations

import argparse
import sys

from occplug.run import runner

from . import paths as check
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
    """Exit 0: exported and within the parity thresholds; 1: exported, outside them; 2: a user mistake."""
    from occplug.export import MAX_LOGIT_DIFF, MIN_CLASS_AGREEMENT, export_checkpoint, one_line, report_path

    ckpt = check.input_file("--ckpt", args.ckpt)  # every path checked before anything is read or written
    out = check.output_file("--out", args.out)
    try:
        report = export_checkpoint(ckpt, args.format, out, samples=args.samples)
    except runner.RunError as exc:
        raise UsageError(str(exc)) from None
    print(one_line(report))
    if not report["passed"]:
        print(
            f"error: the exported model disagrees with the eager one beyond the thresholds (classes agree on >= "
            f"{100 * MIN_CLASS_AGREEMENT:g} %, max |logit diff| <= {MAX_LOGIT_DIFF:g}); see {report_path(out)}",
            file=sys.stderr,
        )
        return 1
    return 0
