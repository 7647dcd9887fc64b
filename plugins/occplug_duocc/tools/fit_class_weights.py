"""DuOcc's occupancy CE class weights as the public code makes them: ``5 / ln(f)`` per class, free halved.

Counts the voxel labels of a config's training split (``occplug data stats``'s counts: every voxel, as the code's
``nusc_class_frequencies``; ``--mask camera`` counts camera-visible ones only) and writes a config overlay that
sets ``model.supervision.<source>.class_weights`` (``occupancy``: the recipes' ``voxel_ce``)::

    python -m occplug_duocc.tools.fit_class_weights -c duocc/stream_agg --out weights.yaml
    occplug fit -c duocc/stream_agg -c weights.yaml

The synthetic recipes ship the overlay this module wrote for the ``default`` world
(``duocc/class_weights/synthetic``); ``duocc/occ3d_nuscenes`` carries the code's own nuScenes values. A class
absent from the split gets the largest weight of the others (:func:`occplug_duocc.tools.class_weights.duocc_class_weights`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import yaml

from occplug.config import ConfigError
from occplug.run import runner


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m occplug_duocc.tools.fit_class_weights",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-c", "--config", action="append", required=True, help="config(s), composed in order")
    parser.add_argument("overrides", nargs="*", help="key=value overrides")
    parser.add_argument("--mask", default="none", choices=["none", "camera"], help="voxels counted (default: every)")
    parser.add_argument("--source", default="occupancy", help="the supervision source to weight (default: occupancy)")
    parser.add_argument("--out", type=Path, required=True, help="the config overlay to write (YAML)")
    parser.add_argument(
        "--unrounded", action="store_true", help="write the float32 weights in full (default: 3 decimals)"
    )
    parser.add_argument(
        "--eps", type=float, default=0.0, help="added to each count before the log (the public code: 0.001; default 0)"
    )
    args = parser.parse_args(argv)
    from occplug.data import class_counts

    from .class_weights import duocc_class_weights

    try:
        if not 0.0 <= args.eps < 1.0:
            raise ConfigError(f"--eps: expected a number in [0, 1) added to the class counts, got {args.eps}")
        cfg = runner.load_config(args.config, args.overrides)
        source = ((cfg.get("model") or {}).get("supervision") or {}).get(args.source)
        if not isinstance(source, dict) or source.get("type") != "voxel_ce":
            raise ConfigError(f"model.supervision.{args.source}: expected a voxel_ce source to weight, got {source!r}")
        dm = runner.build_datamodule(cfg)
        names = list(dm.class_names)
        if "free" not in names:
            raise ConfigError(f"data of {args.config}: no class named 'free' among {names}")
        counts = class_counts(dm.dataset("train"), len(names), mask=args.mask)
        if counts.frames == 0:
            raise ConfigError(f"{args.config}: the training split has no frame with voxel labels")
        weights = duocc_class_weights(counts.counts, free_index=names.index("free"), eps=args.eps)
    except (ConfigError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    plus = f", plus {args.eps:g}" if args.eps else ""
    flags = (["--eps", f"{args.eps:g}"] if args.eps else []) + (["--unrounded"] if args.unrounded else [])
    header = (
        f"# DuOcc occupancy CE class weights (python -m occplug_duocc.tools.fit_class_weights): 5 / ln(f) per class, free\n"
        f"# halved, the public code's rule; f = voxels per class ({args.mask} mask{plus}) over {counts.frames} training frames:\n"
        f"# {[int(c) for c in counts.counts]}\n"
        f"# Made from: {' '.join(['-c ' + c for c in args.config] + list(args.overrides) + flags)}\n"
    )
    # float(w) of a float32 weight is exact: YAML's repr reads back to the same float32
    rounded = [float(w) if args.unrounded else round(float(w), 3) for w in weights]
    body = {"model": {"supervision": {args.source: {"class_weights": rounded}}}}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    runner.write_text_atomic(args.out, header + yaml.safe_dump(body, sort_keys=False, default_flow_style=None))
    print(f"{args.out}: {len(names)} class weights from {counts.frames} frames: {rounded}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
