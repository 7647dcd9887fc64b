"""Scores of predictions that look at no image, on a synthetic preset's validation split.

Prints Occ3D mIoU / geometric IoU (camera mask) for: every voxel ``free``; every voxel the most
frequent occupied class; and the per-voxel most frequent class of the training split (a
"prior map" in the ego frame). A trained model must beat all three to have learnt anything. ``scripts/ceilings.py`` prints the same
floors beside the protocol's ceilings, under every evaluation mask.

    python scripts/trivial_baselines.py [--preset default]
"""

from __future__ import annotations

import argparse

import torch

from occplug.ceilings import training_prior
from occplug.data import collate_frames
from occplug.data.synthetic import SyntheticDataModule
from occplug.metrics import Occ3DMIoU


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="default")
    args = parser.parse_args()
    dm = SyntheticDataModule(preset=args.preset)
    names, free = dm.class_names, dm.free_label
    train, val = dm.dataset("train"), dm.dataset("val")
    prior, most_frequent = training_prior(
        (train[i].voxel_labels for i in range(len(train))), num_classes=len(names), free=free
    )
    predictors = {
        "all free": lambda b: torch.full_like(b.voxel_labels, free, dtype=torch.long),
        f"all {names[most_frequent]}": lambda b: torch.full_like(b.voxel_labels, most_frequent, dtype=torch.long),
        "per-voxel training prior": lambda b: prior.expand(len(b), -1, -1, -1),
    }
    for name, predict in predictors.items():
        metric = Occ3DMIoU(num_classes=len(names), class_names=names, free_label=free, mask="camera")
        for i in range(len(val)):
            batch = collate_frames([val[i]])
            metric.update(predict(batch), batch)
        res = metric.compute()
        print(f"{name:<28} mIoU {res['mIoU'].item():6.2f}   IoU {res['IoU'].item():6.2f}")


if __name__ == "__main__":
    main()
