"""Accuracy by position in the scene: how much a streamed model's history is worth as the stream grows.

For each run directory, the validation split is read in order (the stream state carried as in evaluation, reset at
each scene start) and the module keeps one confusion matrix per position in the scene (frame 0 = the reset frame,
where a streamed model has no history). It prints the run's own metric (the first of ``metrics``, with its evaluation
mask) per position bucket, so a single-frame run and a streamed run can be compared where the stream is short and
where it is long. ``--set`` overrides apply to every run, e.g. longer or more validation scenes, or the stream cut
at every frame (``model.scene.max_gap_s=0.01``). The first metric must keep a confusion matrix (``occ3d_miou``); the
whole validation split is read (``trainer.limit_val_batches`` does not apply)::

    python -m occplug_duocc.tools.stream_gain runs/a-seed0 runs/b-seed0 --set data.frames_per_scene=12 data.val_scenes=8
"""

from __future__ import annotations

import argparse
import copy
import json
import warnings
from pathlib import Path

import torch

from occplug.metrics import confusion_matrix, evaluation_mask
from occplug.run import runner
from occplug.streams import find_streams, set_stream_stage

KEYS = ("mIoU", "mIoU_dynamic", "mIoU_static", "IoU")
OPEN_END = 10**9  # the end of a bucket written "N-"


def last_checkpoint(run: Path) -> Path:
    """``run``'s ``checkpoints/last.ckpt``; ValueError naming the run where there is none."""
    ckpt = run / "checkpoints" / "last.ckpt"
    if not ckpt.is_file():
        raise ValueError(f"{run}: no checkpoints/last.ckpt (not a finished occplug run directory)")
    return ckpt


def parse_buckets(text: str) -> list[tuple[int, int]]:
    """``"0,1,2-3,4-"`` -> ``[(0, 0), (1, 1), (2, 3), (4, OPEN_END)]`` (inclusive position ranges).

    Raises:
        ValueError: a part that is not ``N``, ``N-M`` or ``N-`` with ``0 <= N <= M``.
    """
    out = []
    for part in text.split(","):
        low, dash, high = part.strip().partition("-")
        if not low.isdigit() or (high and not high.isdigit()):
            raise ValueError(f"--buckets: '{part}' is not N, N-M or N- (frame positions, 0 = the reset frame)")
        lo = int(low)
        hi = lo if not dash else (int(high) if high else OPEN_END)
        if hi < lo:
            raise ValueError(f"--buckets: '{part}' has its end before its start")
        out.append((lo, hi))
    return out


def confusions_by_position(run: Path, overrides: list[str], buckets: list[tuple[int, int]]):
    """``(metric, confusion matrices, frame counts)``: the run's first validation metric (a template, its mask and
    classes) and, per position bucket, the confusion matrix and the number of validation frames in it."""
    ckpt = last_checkpoint(run)
    dm, model = runner.build_run(runner.resolve_run_config([], overrides, ckpt))
    model.load_state_dict(runner.load_checkpoint(ckpt)["state_dict"])
    model.eval()
    set_stream_stage(model, "val")
    for _, state in find_streams(model):
        state.clear("val")
    template = next(iter(model.val_metrics.values()))
    if not hasattr(template, "confmat"):
        raise ValueError(
            f"{run}: its first metric ({type(template).__name__}) keeps no confusion matrix; "
            "put occ3d_miou first (--set 'metrics=[occ3d_miou]')"
        )
    confmats = [torch.zeros_like(template.confmat) for _ in buckets]
    dm.prepare_data()
    dm.setup("validate")
    frames = [0] * len(buckets)
    with torch.no_grad():
        for batch in dm.val_dataloader():
            pred = model.predict_occupancy(batch)
            valid = evaluation_mask(batch, template.mask)
            for b, position in enumerate(batch.frame_index.tolist()):
                for i, (lo, hi) in enumerate(buckets):
                    if lo <= position <= hi:
                        keep = None if valid is None else valid[b]
                        confmats[i] += confusion_matrix(pred[b], batch.voxel_labels[b], template.num_classes, keep)
                        frames[i] += 1
    return template, confmats, frames


def results_by_position(run: Path, overrides: list[str], buckets: list[tuple[int, int]]) -> list[dict[str, float]]:
    """The run's first metric over the validation frames of each position bucket (the run's evaluation mask),
    with ``frames``, the bucket's frame count (a bucket with no frame has only that)."""
    template, confmats, frames = confusions_by_position(run, overrides, buckets)
    out = []
    for cm, n in zip(confmats, frames, strict=True):
        metric = copy.deepcopy(template)
        metric.confmat = cm
        with warnings.catch_warnings():  # the confusion matrix was set directly, not through update()
            warnings.filterwarnings("ignore", message=".*compute.*called before.*update.*")
            res = {k: float(v) for k, v in metric.compute().items() if k in KEYS} if n else {}
        out.append({**res, "frames": n})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(
        prog="python -m occplug_duocc.tools.stream_gain",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("runs", nargs="+", type=Path, help="run directories (each with checkpoints/last.ckpt)")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="overrides for every run")
    parser.add_argument(
        "--buckets", default="0,1,2,3,4,5-", help="position ranges, e.g. '0,1-2,3-' (default: %(default)s)"
    )
    parser.add_argument("--json", type=Path, help="also write {run: [bucket results]} here")
    args = parser.parse_args()
    try:
        buckets = parse_buckets(args.buckets)
        for run in args.runs:  # every run checked before the first is read
            last_checkpoint(run)
    except ValueError as exc:
        parser.error(str(exc))
    names = [f"{lo}" if lo == hi else (f"{lo}+" if hi >= OPEN_END else f"{lo}-{hi}") for lo, hi in buckets]
    payload = {}
    for run in args.runs:
        try:
            rows = results_by_position(run, args.set, buckets)
        except (runner.RunError, ValueError) as exc:  # a config mistake (ConfigError) is a ValueError
            parser.error(str(exc).splitlines()[0])
        payload[str(run)] = [{"positions": n, **r} for n, r in zip(names, rows, strict=True)]
        print(f"{run}:")
        print("| frame in scene | frames | " + " | ".join(KEYS) + " |")
        print("|--:|--:|" + "--:|" * len(KEYS))
        for name, r in zip(names, rows, strict=True):
            print(f"| {name} | {r['frames']} | " + " | ".join(f"{r.get(k, float('nan')):.2f}" for k in KEYS) + " |")
    if args.json:
        args.json.write_text(json.dumps({"overrides": args.set, "runs": payload}, indent=1) + "\n")


if __name__ == "__main__":
    main()
