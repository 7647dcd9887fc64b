"""The ideal field's and the floor's scores through the trained models' own metrics: Occ.IoU / mIoU (camera mask), RayIoU.

``scripts/ceilings.py`` scores the ideal field (the world's exact solids and a ground slab, read at voxel centres
or at k³ sub-samples) by Occ.IoU and mIoU only. This script feeds the same readouts, frame by frame of a synthetic
world's validation split, to ``occ3d_miou`` and ``rayiou`` as configured in a run (``exclude_classes: [others]``),
so a trained model's Occ.RayIoU can be printed beside its ceiling; the floor (``prior``: the per-voxel most frequent
class of the training labels, as ``scripts/ceilings.py``'s) is scored the same way::

    python scripts/ideal_rayiou.py --preset aligned --readouts center any3 --json results/queryocc/calibrated/ideal_field.json

Bad input (an unknown preset or readout) is one ``error:`` line and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

KEYS = ("IoU", "mIoU", "RayIoU", "RayIoU_geometry", "RayIoU_dynamic", "mIoU_excl", "RayIoU_excl")
#: ``--results`` files' keys (the QueryOcc ablation's columns) -> metric keys
COLUMNS = {
    "Sem.RayIoU": "RayIoU",
    "Dyn.RayIoU": "RayIoU_dynamic",
    "Occ.RayIoU": "RayIoU_geometry",
    "Sem.IoU": "mIoU",
    "Occ.IoU": "IoU",
}
FLOOR = "prior"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="aligned")
    parser.add_argument("--readouts", nargs="+", default=["center", "any3"])
    parser.add_argument("--ground-shell", type=float, default=0.5)
    parser.add_argument("--no-floor", action="store_true", help="skip the per-voxel training prior (the floor)")
    parser.add_argument("--json", default=None, help="write the scores here")
    parser.add_argument(
        "--results",
        help="also write ideal_<readout>-seed<k>.json and prior_floor-seed<k>.json here (the same numbers for every "
        "--seeds k: nothing is trained; beside an ablation's per-seed files for scripts/claims_tables.py)",
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = parser.parse_args(argv)

    from occplug.ceilings import parse_readout, read_voxels, training_prior
    from occplug.data.synthetic import SyntheticDataModule, build_scene
    from occplug.data.synthetic.testbed import scene_field_samples
    from occplug.metrics import Occ3DMIoU, RayIoU

    try:
        readouts = [parse_readout(r) for r in args.readouts]
        dm = SyntheticDataModule(preset=args.preset, batch_size=1)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    start = time.perf_counter()
    config, names, free = dm.world_config, list(dm.class_names), dm.free_label
    names_scored = [r.name for r in readouts] + ([] if args.no_floor else [FLOOR])
    metrics = {
        name: [
            Occ3DMIoU(num_classes=len(names), class_names=names, free_label=free, exclude_classes=["others"]),
            RayIoU(
                num_classes=len(names), class_names=names, free_label=free, grid=dm.grid, exclude_classes=["others"]
            ),
        ]
        for name in names_scored
    }
    prior = None
    if not args.no_floor:  # the per-voxel most frequent class of the training labels (scripts/ceilings.py's floor)
        train = dm.dataset("train")
        prior = training_prior((train[i].voxel_labels for i in range(len(train))), len(names), free)[0]
    ds = dm.dataset("val")
    frames = config.frames("val")
    scene = None
    for i in range(len(ds)):
        s, f = divmod(i, frames)  # item i is frame i % F of scene i // F
        if f == 0:
            scene = build_scene(config, "val", s)
        batch = dm.collate([ds[i]])
        by_k = {}
        for r in readouts:
            if r.k not in by_k:
                by_k[r.k] = scene_field_samples(config, scene, f, r.k, ground_shell=args.ground_shell)
            pred = read_voxels(by_k[r.k], r.rule, free, len(names))[None]
            for m in metrics[r.name]:
                m.update(pred.long(), batch)
        if prior is not None:
            for m in metrics[FLOOR]:
                m.update(prior[None].long(), batch)
    report = {"preset": args.preset, "frames": len(ds), "ground_shell": args.ground_shell, "readouts": {}}
    for name, ms in metrics.items():
        out = {}
        for m in ms:
            out.update({k: float(v) for k, v in m.compute().items()})
        report["readouts"][name] = {k: out[k] for k in KEYS if k in out}
    report["seconds"] = round(time.perf_counter() - start, 1)
    print(f"{'readout':<10} " + " ".join(f"{k:>16}" for k in KEYS))
    for name, v in report["readouts"].items():
        print(f"{name:<10} " + " ".join(f"{v.get(k, float('nan')):16.2f}" for k in KEYS))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(report, indent=1) + "\n")
        print(f"wrote {args.json}")
    if args.results:
        from occplug.run.bench import write_seed_result

        settings = {"preset": args.preset, "ground_shell": args.ground_shell}
        for name, v in report["readouts"].items():
            row = "prior_floor" if name == FLOOR else f"ideal_{name}"
            for seed in args.seeds:
                write_seed_result(args.results, row, seed, {c: v[k] for c, k in COLUMNS.items()}, settings)
    return 0


if __name__ == "__main__":
    sys.exit(main())
