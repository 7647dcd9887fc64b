"""DuOcc's detector anchors as the public code makes them: k-means of the training boxes' centres.

Reads every frame of a config's training split, keeps the boxes of the detector's classes
(``model.scene.query_agg.detection_classes``; the code takes every box of its info file, which holds nuScenes' ten
detection classes) whose centre lies within ``--max-distance`` metres of the ego (the norm of ``(x, y, z)``, as the
code; it uses 42 m; default: the centre inside the config's grid in x and y), and writes a config overlay with
``anchor_centres`` (k-means of the centres, k = the detector's ``num_queries`` or ``--queries``) and
``anchor_size`` (the mean box size)::

    python -m occplug_duocc.tools.fit_anchors -c duocc/full --out anchors.yaml
    occplug fit -c duocc/full -c anchors.yaml

``duocc/full`` ships the overlay this module wrote for the synthetic ``default`` world
(``duocc/anchors/synthetic``); for real data, run it on your recipe (e.g. ``-c duocc/occ3d_nuscenes``, 900
queries). It reads whole frames (images too): every frame of a synthetic world is rendered once (then cached), and
on real data this takes as long as one pass over the training split. ``duocc/full`` with another world or grid
still starts from the default world's anchors: make an overlay for it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
import yaml

from occplug.config import ConfigError
from occplug.run import runner


def detection_classes(agg: dict, class_names: tuple[str, ...]) -> list[int]:
    """The label ids the detector of a ``query_agg`` node classifies: its ``detection_classes``, else the
    data's ``dynamic`` class group (as ``duocc_stream`` resolves them)."""
    from ..blocks.queryagg import QueryAggSettings, resolve_detection_classes

    given = agg.get("detection_classes")
    settings = QueryAggSettings(detection_classes=None if given is None else tuple(int(c) for c in given))
    try:
        return list(resolve_detection_classes(settings, class_names).detection_classes)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def training_boxes(cfg: dict, classes: list[int] | None, max_distance: float | None) -> tuple[torch.Tensor, list[int]]:
    """``(M, 9)`` ego-frame boxes of ``classes`` over the training split (inside the grid, or the distance), and
    ``classes`` (None: those of the config's ``model.scene.query_agg``, :func:`detection_classes`)."""
    dm = runner.build_datamodule(cfg)
    if classes is None:
        classes = detection_classes(cfg["model"]["scene"]["query_agg"], tuple(dm.class_names))
    grid = dm.grid
    dataset = dm.dataset("train")
    wanted = torch.tensor(classes)
    lo, hi = torch.tensor(grid.range[:2]), torch.tensor(grid.range[3:5])
    kept = []
    for i in range(len(dataset)):
        frame = dataset[i]
        if frame.boxes is None or frame.box_labels is None or not len(frame.boxes):
            continue
        boxes = frame.boxes[torch.isin(frame.box_labels, wanted)]
        if max_distance is not None:  # the code's rule: the norm of the centre (x, y, z)
            near = boxes[:, :3].norm(dim=1) <= max_distance
        else:
            near = ((boxes[:, :2] >= lo) & (boxes[:, :2] <= hi)).all(1)
        kept.append(boxes[near])
    return (torch.cat(kept) if kept else torch.zeros(0, 9)), classes


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m occplug_duocc.tools.fit_anchors",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-c", "--config", action="append", required=True, help="config(s), composed in order")
    parser.add_argument("overrides", nargs="*", help="key=value overrides")
    parser.add_argument("--queries", type=int, default=None, help="anchors to make (default: the detector's)")
    parser.add_argument("--max-distance", type=float, default=None, help="metres from the ego (default: the grid)")
    parser.add_argument("--seed", type=int, default=0, help="k-means++ seed")
    parser.add_argument("--out", type=Path, required=True, help="the config overlay to write (YAML)")
    args = parser.parse_args(argv)
    from .anchors import kmeans_anchors

    try:
        cfg = runner.load_config(args.config, args.overrides)
        agg = (cfg["model"].get("scene") or {}).get("query_agg")
        if not isinstance(agg, dict):
            raise ConfigError("model.scene.query_agg: the config has no DuOcc detector (use e.g. -c duocc/full)")
        k = int(args.queries if args.queries is not None else agg["detector"].get("num_queries", 64))
        if k < 1:
            raise ConfigError(f"--queries: expected an int >= 1, got {k}")
        boxes, classes = training_boxes(cfg, None, args.max_distance)
        if boxes.shape[0] < k:
            raise ConfigError(f"{args.config}: the training split holds {boxes.shape[0]} boxes, fewer than {k} anchors")
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    centres, size = kmeans_anchors(boxes, k, seed=args.seed)
    where = f"within {args.max_distance:g} m" if args.max_distance is not None else "inside the grid"
    header = (
        f"# DuOcc detector anchors (python -m occplug_duocc.tools.fit_anchors): k-means (k={k}, seed {args.seed}) of\n"
        f"# {boxes.shape[0]} ego-frame centres of the training boxes {where}, classes {classes};\n"
        f"# size = the mean box size. Made from: -c {' -c '.join(args.config)} {' '.join(args.overrides)}\n"
    )
    body = {
        "model": {
            "scene": {
                "query_agg": {
                    "detector": {
                        "num_queries": k,
                        "anchor_size": [round(float(v), 3) for v in size],
                        "anchor_centres": [[round(float(v), 3) for v in c] for c in centres],
                    }
                }
            }
        }
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    runner.write_text_atomic(args.out, header + yaml.safe_dump(body, sort_keys=False, default_flow_style=None))
    print(f"{args.out}: {k} anchors from {boxes.shape[0]} boxes; mean size {[round(float(v), 2) for v in size]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
