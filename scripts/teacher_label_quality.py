#!/usr/bin/env python
"""How good were a phased run's teacher pseudo labels? Each file a teacher wrote (``<run>/pseudo_labels/*/``) scored
against its frame's true voxel labels, inside the camera mask, over the frames that have a file.

Prints one JSON object: files scored, per-class IoU of the pseudo labels (classes present in the truth of those
frames), their mIoU and its dynamic part, the occupied-vs-free IoU, and the share of voxels at or above the
confidence threshold the student phase used (its ``pseudo_labels_from.confidence_threshold``) with the mIoU of those
voxels alone. The true labels come from the teacher phase's data config with ``data.label_fraction=1.0``::

    python scripts/teacher_label_quality.py runs/ablate_mix/duocc_b_three_phase_10pct-seed0 [--threshold 0.7]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from occplug.data import class_groups
from occplug.run import runner


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a run directory of phases with a pseudo_labels folder")
    parser.add_argument("--threshold", type=float, default=0.7, help="confidence kept by the student (default 0.7)")
    args = parser.parse_args(argv)
    folders = sorted(p for p in (args.run / "pseudo_labels").glob("*") if p.is_dir()) if args.run.is_dir() else []
    if not folders:
        raise SystemExit(f"error: {args.run}: no pseudo_labels/<folder> (a run whose phases wrote teacher labels)")
    folder = folders[0]
    teacher = json.loads((folder / "meta.json").read_text())["teacher"]  # the phase that wrote the folder
    cfg = runner.load_config([str(args.run / teacher / "config.yaml")], ["data.label_fraction=1.0"])
    dm = runner.build_datamodule(cfg)  # the frames' true labels; no model is needed
    names = list(dm.class_names)
    dynamic_names = {names[i] for i in (class_groups(names) or {}).get("dynamic", ())}  # as the metrics group them
    free = len(names) - 1
    inter, union, truth = (np.zeros(len(names)) for _ in range(3))
    inter_k, union_k = np.zeros(len(names)), np.zeros(len(names))
    kept = observed = scored = 0
    occ = np.zeros(2)
    dataset = dm.dataset("train")
    for i in range(len(dataset)):
        frame = dataset[i]
        path = folder / f"{frame.token}.npz"
        if not path.is_file():
            continue
        scored += 1
        with np.load(path) as arrays:  # the layout of occplug.data.teacher_labels: labels uint8, confidence float16
            labels, confidence = arrays["labels"], arrays["confidence"]
        pred, gt = labels.astype(np.int64), frame.voxel_labels.numpy().astype(np.int64)
        mask = frame.mask_camera.numpy() if frame.mask_camera is not None else np.ones_like(gt, dtype=bool)
        keep = (confidence.astype(np.float32) >= args.threshold) & mask
        for k in range(len(names)):
            p, g = (pred == k) & mask, (gt == k) & mask
            inter[k] += (p & g).sum()
            union[k] += (p | g).sum()
            truth[k] += g.sum()
            inter_k[k] += (p & g & keep).sum()
            union_k[k] += ((p | g) & keep).sum()
        kept += keep.sum()
        observed += mask.sum()
        p_occ, g_occ = (pred != free) & mask, (gt != free) & mask
        occ += [(p_occ & g_occ).sum(), (p_occ | g_occ).sum()]
    present = [k for k in range(free) if truth[k] > 0]
    iou = {names[k]: 100 * inter[k] / union[k] for k in present}
    iou_kept = [100 * inter_k[k] / union_k[k] for k in present if union_k[k] > 0]
    dynamic = [v for n, v in iou.items() if n in dynamic_names]
    print(json.dumps({
        "run": str(args.run), "folder": folder.name, "files_scored": scored,
        "mIoU": float(np.mean(list(iou.values()))), "mIoU_dynamic": float(np.mean(dynamic)) if dynamic else None,
        "IoU_occupied": float(100 * occ[0] / max(occ[1], 1)),
        f"share_at_or_above_{args.threshold}": float(kept / max(observed, 1)),
        f"mIoU_at_or_above_{args.threshold}": float(np.mean(iou_kept)) if iou_kept else None,
        "IoU_per_class": {n: round(float(v), 2) for n, v in iou.items()},
    }, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
