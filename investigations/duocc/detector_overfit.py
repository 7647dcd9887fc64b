"""Can DuOcc's detector fit a few training frames? Bug or budget, for its ~1 % validation mAP.

Trains a DuOcc config (default ``duocc/det_only``) with its own losses on the first ``--batches`` training batches
only, in stream order, over and over, and prints the detector's mAP (``detection_map``, nuScenes centre distance)
on those same batches as it goes, then on the validation split. Fitting a few frames shows that the Hungarian
matching, the loss and the box decoding agree with the metric (the training targets and the metric's ground truth
both come from ``detection_targets``, so an error shared by both could still be memorised; an above-chance AP on
unseen validation frames is what shows the boxes line up with the images). One that fits its frames but not the
validation split is limited by data and budget::

    python investigations/duocc/detector_overfit.py                       # the first 12 training batches, 40 passes
    python investigations/duocc/detector_overfit.py --batches 4 --passes 60 --set data.num_cameras=1
    python investigations/duocc/detector_overfit.py --run runs/duocc_ablate/full-seed0 --batches 48

``--run`` evaluates a trained run's last checkpoint on the first training and validation batches, training
nothing: a detector that scores far higher on its training frames than on the validation split has memorised
them; one that scores low on both has not fitted the data (budget).

Every pass clears the stream state first, so each pass sees the same sequence. The optimizer is the config's
(``build_optimizer``, its base learning rate: no batch scaling, no schedule), gradients clipped at the config's
``trainer.gradient_clip_val``.
"""

from __future__ import annotations

import argparse
import itertools
import time
from pathlib import Path

import torch

from occplug.data import OCC3D_CLASSES
from occplug.run import runner
from occplug.run.training import build_optimizer
from occplug.streams import find_streams, set_stream_stage
from occplug_duocc.tools.detection_eval import stream_detection_map


def detector_map(model, batches: list, stage: str) -> dict:
    """:func:`~occplug_duocc.tools.detection_eval.stream_detection_map` over ``batches`` in order, with ``"names"``: the
    class name of each detection class index."""
    result = stream_detection_map(model, batches, stage)
    result["names"] = [OCC3D_CLASSES[c] for c in result["classes"]]
    return result


def per_class(result: dict) -> dict[str, float]:
    """``{class name: AP %}`` of the classes in the ground truth, one decimal."""
    return {result["names"][c]: round(100 * a, 1) for c, a in result["AP"].items()}


def main() -> None:
    parser = argparse.ArgumentParser(
        prog="python investigations/duocc/detector_overfit.py",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-c", "--config", default="duocc/det_only")
    parser.add_argument("--batches", type=int, default=12, help="training batches to fit (the first, in order)")
    parser.add_argument("--passes", type=int, default=40, help="passes over those batches")
    parser.add_argument("--every", type=int, default=10, help="print the training-batch mAP every this many passes")
    parser.add_argument("--val-every", action="store_true", help="print the validation mAP every --every passes too")
    parser.add_argument("--val-batches", type=int, default=None, help="validation batches (default: all)")
    parser.add_argument("--run", help="a finished run folder: evaluate its last checkpoint, train nothing")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", nargs="*", default=[], help="key=value overrides")
    args = parser.parse_args()

    torch.manual_seed(args.seed)
    if args.run:
        import yaml

        run = Path(args.run)
        cfg = runner.load_config([], args.set, saved=yaml.safe_load((run / "config.yaml").read_text()))
        dm, model = runner.build_run(cfg)
        last = run / "checkpoints" / "last.ckpt"
        ckpt = last if last.is_file() else max((run / "checkpoints").glob("*.ckpt"), key=lambda f: f.stat().st_mtime)
        model.load_state_dict(runner.load_checkpoint(ckpt)["state_dict"])
        args.passes, args.config = 0, str(ckpt)
    else:
        cfg = runner.load_config([args.config], [f"seed={args.seed}", *args.set])
        dm, model = runner.build_run(cfg)
    dm.prepare_data()
    dm.setup("fit")
    train = list(itertools.islice(dm.train_dataloader(), args.batches))
    val = list(itertools.islice(dm.val_dataloader(), args.val_batches))
    n_boxes = sum(len(b.boxes[i]) if b.boxes is not None else 0 for b in train for i in range(len(b)))
    passes = "" if args.run else f" for {args.passes} passes"
    print(
        f"{args.config}: {'scoring' if args.run else 'fitting'} {len(train)} training batches "
        f"({sum(len(b) for b in train)} frames, {n_boxes} boxes of every class){passes}; {len(val)} validation batches",
        flush=True,
    )
    optimizer = build_optimizer([p for p in model.parameters() if p.requires_grad], cfg.get("optimizer"))
    clip = (cfg.get("trainer") or {}).get("gradient_clip_val")
    start = time.monotonic()
    if args.run:
        result = detector_map(model, train, "train")
        print(f"training batches: mAP {100 * result['mAP']:.2f} %, AP per class {per_class(result)}", flush=True)
    for p in range(1, args.passes + 1):
        model.train()
        set_stream_stage(model, "train")
        for _, state in find_streams(model):
            state.clear("train")
        totals: dict[str, float] = {}
        for batch in train:
            losses = model.losses(batch, model(batch))
            loss = torch.stack(list(losses.values())).sum()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if clip:
                torch.nn.utils.clip_grad_norm_(model.parameters(), float(clip))
            optimizer.step()
            for k, v in losses.items():
                totals[k] = totals.get(k, 0.0) + float(v.detach()) / len(train)
        if p % args.every == 0 or p == args.passes:
            result = detector_map(model, train, "train")
            det = {k.split("/", 1)[1]: round(v, 3) for k, v in totals.items() if k.startswith("detection/")}
            print(
                f"pass {p:4d} ({time.monotonic() - start:5.0f} s): train-batch mAP {100 * result['mAP']:.2f} %, "
                f"AP per class {per_class(result)}, AP@ {{{', '.join(f'{t}: {100 * a:.1f}' for t, a in result['AP@'].items())}}}, "
                f"detection loss {det}",
                flush=True,
            )
            if args.val_every:
                held = detector_map(model, val, "val")
                print(
                    f"pass {p:4d}: validation mAP {100 * held['mAP']:.2f} %, AP per class {per_class(held)}", flush=True
                )
    result = detector_map(model, val, "val")
    print(
        f"validation ({len(val)} batches): mAP {100 * result['mAP']:.2f} %, AP per class {per_class(result)}",
        flush=True,
    )


if __name__ == "__main__":
    main()
