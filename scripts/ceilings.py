"""Floor, ceilings and history headroom of a synthetic world's evaluation protocols, in one table.

For each evaluation mask (``camera``: the rig's camera mask, ``camera1``: the front camera's, ``lidar``,
``none``: every voxel) it prints Occ.IoU / mIoU of the floor (all free, all of the most frequent class,
the per-voxel training prior), of the ideal field read through each readout (``center``: voxel
centres, as a query decoder is read; ``any2`` / ``vote2``: 2 x 2 x 2 sub-samples) and of the
perfect-depth lift (true depth and 2D classes at the feature stride; the rig's cameras and the front
camera alone), then the history headroom per protocol and the agents' pixel heights per class.

    python scripts/ceilings.py --preset default --json results/testbed/default.json
    python scripts/ceilings.py --preset default --set grid='{range: [-24, -24, -1.4, 24, 24, 5.0], voxel_size: 0.8}'

Bad input (an unknown preset, knob or readout) is one ``error:`` line and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import yaml


def _world(preset: str, sets: list[str]) -> Any:
    from occplug.data.synthetic import preset as get_preset

    config = get_preset(preset)
    changes = {}
    for item in sets:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--set {item!r}: expected KNOB=VALUE (YAML value)")
        changes[key] = yaml.safe_load(value)
    try:
        return config.replace(**changes)
    except TypeError as exc:
        raise ValueError(f"--set: {exc}") from exc


def _table(report: dict[str, Any]) -> str:
    lines = [f"{'mask':<8} {'prediction':<34} {'Occ.IoU':>8} {'mIoU':>7}"]
    for mask in report["floor"]:
        rows = [(f"floor: {k}", v) for k, v in report["floor"][mask].items()]
        rows += [(f"ideal field: {k}", v) for k, v in report["ideal"][mask].items()]
        rows += [(f"perfect depth: {k}", v) for k, v in report["perfect_depth"].get(mask, {}).items()]
        rows += [("one LiDAR sweep, voxelised", report["lidar_sweep"][mask])]
        for name, v in rows:
            lines.append(f"{mask:<8} {name:<34} {v['IoU']:8.2f} {v['mIoU']:7.2f}")
    lines.append("")
    lines.append(
        f"{'history headroom (observe -> score)':<36} {'scored':>9} {'now %':>7} {'earlier-only %':>15} "
        f"{'t+-1-only %':>12}"
    )
    for name, h in report["headroom"].items():
        lines.append(
            f"{name:<36} {h['scored']:>9} {h['share_observed_now']:7.2f} {h['share_earlier_only']:15.2f} "
            f"{h['share_adjacent_only']:12.2f}"
        )
    if report.get("pixel_heights"):
        lines.append("")
        lines.append(f"{'class':<22} {'agents':>6} {'median px':>10} {'p10 px':>7} {'p90 px':>7} {'median m':>9}")
        for cls, v in report["pixel_heights"].items():
            lines.append(
                f"{cls:<22} {v['count']:>6} {v['median_px']:10.1f} {v['p10_px']:7.1f} {v['p90_px']:7.1f} "
                f"{v['median_distance_m']:9.1f}"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="default")
    parser.add_argument("--set", action="append", default=[], metavar="KNOB=VALUE", help="change a world knob")
    parser.add_argument("--readouts", default="center,any2,vote2")
    parser.add_argument("--masks", default="camera,camera1,lidar,none")
    parser.add_argument(
        "--depth-stride", type=int, default=8, help="feature stride of the perfect-depth lift (0: skip)"
    )
    parser.add_argument("--ground-shell", type=float, default=0.5)
    parser.add_argument("--train-scenes", type=int, default=None, help="scenes of the floor's prior (default all)")
    parser.add_argument("--eval-scenes", type=int, default=None)
    parser.add_argument("--cache-dir", default=None, help="frame cache (default the synthetic world's)")
    parser.add_argument("--json", default=None, help="write the report here")
    args = parser.parse_args(argv)

    from occplug.data.synthetic import default_cache_dir
    from occplug.data.synthetic.testbed import measure, object_pixel_heights

    try:
        config = _world(args.preset, args.set)
        start = time.perf_counter()
        report = measure(
            config,
            readouts=[r for r in args.readouts.split(",") if r],
            masks=[m for m in args.masks.split(",") if m],
            ground_shell=args.ground_shell,
            depth_stride=args.depth_stride or None,
            train_scenes=args.train_scenes,
            eval_scenes=args.eval_scenes,
            cache_dir=args.cache_dir or default_cache_dir(),
            progress=lambda line: print(line, file=sys.stderr),
        )
        report["pixel_heights"] = object_pixel_heights(config, scenes=args.eval_scenes)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    report["preset"], report["set"] = args.preset, args.set
    report["seconds"] = round(time.perf_counter() - start, 1)
    print(_table(report))
    if args.json:
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(report, indent=1) + "\n")
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
