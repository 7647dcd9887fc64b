"""The ideal field's scores through the trained models' own metrics: Occ.IoU / mIoU (camera mask) and RayIoU.

``scripts/ceilings.py`` scores the ideal field (the world's exact solids and a ground slab, read at voxel centres
or at k³ sub-samples) by Occ.IoU and mIoU only. This script feeds the same readouts, frame by frame of a synthetic
world's validation split, to ``occ3d_miou`` and ``rayiou`` as configured in a run (``exclude_classes: [others]``),
so a trained model's Occ.RayIoU can be printed beside its ceiling::

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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="aligned")
    parser.add_argument("--readouts", nargs="+", default=["center", "any3"])
    parser.add_argument("--ground-shell", type=float, default=0.5)
    parser.add_argument("--json", default=None, help="write the scores here")
    args = parser.parse_args(argv)

    from occplug.ceilings import parse_readout, read_voxels
    from occplug.data.synthetic import SyntheticDataModule
    from occplug.data.synthetic.field import scene_field_samples
    from occplug.data.synthetic.world import build_scene
    from occplug.metrics import Occ3DMIoU, RayIoU

    try:
        readouts = [parse_readout(r) for r in args.readouts]
        dm = SyntheticDataModule(preset=args.preset, batch_size=1)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    start = time.perf_counter()
    config, names, free = dm.world_config, list(dm.class_names), dm.free_label
    metrics = {
        r.name: [
            Occ3DMIoU(num_classes=len(names), class_names=names, free_label=free, exclude_classes=["others"]),
            RayIoU(
                num_classes=len(names), class_names=names, free_label=free, grid=dm.grid, exclude_classes=["others"]
            ),
        ]
        for r in readouts
    }
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
