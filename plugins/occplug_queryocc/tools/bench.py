"""QueryOcc's contracted BEV against dense BEVs as the supervised range grows, on the ``long_range`` world.

The label grid (what is scored) is the ``long_range`` world's 128 x 128 x 8 voxels of 0.8 m over +-51.2 m. The
supervised range R is the half-extent in x and y of the points the query source keeps
(``long_range: false, near_range: R``), and the depth bins reach ``depth_far = 1.25 R``. The BEV planes:

* ``contracted``: QueryOcc's plane, 128 x 128 cells; the middle 102 linear over +-51.2 m (1 m cells), the rest
  contracts everything beyond. Memory and cells do not depend on R.
* ``dense_near``: 128 x 128 cells of 0.8 m over the label grid only; points and queries beyond it read nothing.
* ``dense_full``: 128 x 128 cells spread over +-R (the same memory as ``contracted``; cells 2R/128 m).
* ``dense_fine`` (time and memory only, not trained): a dense plane over +-R at the contracted plane's near-field
  resolution, 1 m -- the memory a dense BEV needs to keep the near-field detail (2R x 2R cells).

Time and memory: per range, the four BEVs go through :func:`occplug.run.bench.run_bench` together -- each model in
its own process, interleaved round by round, so a range's rows are measured side by side (training step at batch
1, data loading excluded). Memory is the process's peak RSS on CPU (CUDA's peak allocation on a GPU), so it
includes the data and the interpreter: compare rows, not absolute values. Accuracy: at ``--train-ranges`` the
three equal-memory planes are trained with ``occplug fit -c queryocc/base`` and the overrides above (no voxel
labels, pseudo points, ``--epochs`` epochs), each in its own process; any finished run directory of a (range,
plane) in ``--out`` is scored (mean over its seeds).

    python -m occplug_queryocc.tools.bench                                    # R = 50..200 m; accuracy at 50 and 200
    python -m occplug_queryocc.tools.bench --ranges 50 --train-ranges 50 --epochs 1   # a smoke run
    python -m occplug_queryocc.tools.bench --train-ranges                     # time and memory only

The ``long_range`` world is generated once (about 25 s per frame per core; 44 frames) into the world cache.
Results go to ``--out`` (default ``runs/queryocc_bench``); a finished run directory is reused.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from occplug.run.bench import fit_in_process

VARIANTS = ("contracted", "dense_near", "dense_full", "dense_fine")
ACCURACY = ("RayIoU", "RayIoU_geometry", "mIoU", "IoU")
LABEL_HALF = 51.2  # the long_range world's label grid: +-51.2 m at 0.8 m
CELLS = 128


def plane(variant: str, r: float) -> str:
    """The ``model.view_transform.grid`` override of one variant at supervised range ``r`` (metres)."""
    if variant == "contracted":  # kappa 0.8: the near field +-51.2 m takes the middle 0.8 of +-64 -> 1 m cells
        half = LABEL_HALF / 0.8
        return (
            f"{{range: [-{half}, -{half}, -1.0, {half}, {half}, 5.4], voxel_size: [1.0, 1.0, 6.4], "
            f"contraction: {{near: {LABEL_HALF}, kappa: 0.8}}}}"
        )
    if variant == "dense_near":
        size = 2 * LABEL_HALF / CELLS
        return f"{{range: [-{LABEL_HALF}, -{LABEL_HALF}, -1.0, {LABEL_HALF}, {LABEL_HALF}, 5.4], voxel_size: [{size}, {size}, 6.4]}}"
    if variant == "dense_full":
        size = 2 * r / CELLS
        return f"{{range: [-{r}, -{r}, -1.0, {r}, {r}, 5.4], voxel_size: [{size}, {size}, 6.4]}}"
    if variant == "dense_fine":
        return f"{{range: [-{r}, -{r}, -1.0, {r}, {r}, 5.4], voxel_size: [1.0, 1.0, 6.4]}}"
    raise ValueError(variant)


def mean(values: list[float]) -> float | None:
    return sum(values) / len(values) if values else None


def overrides(variant: str, r: float, seed: int, epochs: int) -> list[str]:
    return [
        f"seed={seed}",
        "data.preset=long_range",
        "grid={range: [-51.2, -51.2, -1.0, 51.2, 51.2, 5.4], voxel_size: 0.8}",
        f"model.view_transform.grid={plane(variant, r)}",
        f"model.view_transform.depth_far={1.25 * r}",
        "model.supervision.queries.long_range=false",
        f"model.supervision.queries.near_range={r}",
        f"trainer.max_epochs={epochs}",
        "trainer.enable_progress_bar=false",
    ]


def train(variant: str, r: float, seed: int, args: argparse.Namespace) -> Path:
    out = Path(args.out) / f"{variant}-R{r:g}-seed{seed}"
    if (out / "metrics.json").is_file():
        return out
    return fit_in_process("queryocc/base", overrides(variant, r, seed, args.epochs), out, out.name)


def main() -> None:
    parser = argparse.ArgumentParser(
        prog="python -m occplug_queryocc.tools.bench",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--ranges", type=float, nargs="+", default=[50.0, 100.0, 150.0, 200.0], help="supervised ranges R (m)"
    )
    parser.add_argument(
        "--train-ranges",
        type=float,
        nargs="*",
        default=[50.0, 200.0],
        help="ranges whose BEVs are also trained for accuracy",
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--epochs", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3, help="latency and training rounds per model")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", default="runs/queryocc_bench")
    args = parser.parse_args()

    from occplug.run.bench import BenchSettings, resolve_target, run_bench

    settings = BenchSettings(
        repeats=args.repeats, warmup=1, train_repeats=args.repeats, batch_size=1, device=args.device
    )
    start = time.monotonic()
    for r in args.train_ranges:
        for variant in VARIANTS[:3]:
            for seed in args.seeds:
                train(variant, r, seed, args)
    rows = []
    for r in args.ranges:  # one interleaved measurement per range: its four BEVs side by side
        targets = [
            resolve_target("queryocc/base", settings, overrides(variant, r, 0, args.epochs)) for variant in VARIANTS
        ]
        report = run_bench(targets, settings, progress=lambda line: print(line, file=sys.stderr))
        for variant, row in zip(VARIANTS, report.rows, strict=True):
            finished = sorted(Path(args.out).glob(f"{variant}-R{r:g}-seed*/metrics.json"))  # trained now or before
            scores = [json.loads(path.read_text()) for path in finished]
            rows.append(
                {
                    "R": r,
                    "variant": variant,
                    "cells": int(2 * r) ** 2 if variant == "dense_fine" else CELLS**2,
                    "train_step_ms": row.train_step_ms,
                    "train_memory_mib": row.train_memory_mib,
                    "latency_ms": row.latency_ms,
                    "params": row.params,
                    **{k: mean([m[k] for m in scores if m.get(k) is not None]) for k in ACCURACY},
                }
            )
    lines = [
        f"{report.machine}; {report.device}; torch {report.versions.get('torch', '?')}; long_range world, label grid "
        f"+-51.2 m; accuracy at R = {args.train_ranges} (seeds {args.seeds}, {args.epochs} epochs, no voxel labels); "
        f"training step at batch 1; {time.monotonic() - start:.0f} s",
        "",
        "| R (m) | BEV | cells | train step (ms) | train peak RSS (MiB) | latency (ms) | Sem.RayIoU | Occ.RayIoU | Sem.IoU | Occ.IoU |",
        "|--:|---|--:|--:|--:|--:|--:|--:|--:|--:|",
    ]

    def num(row: dict, key: str) -> str:
        return "—" if row[key] is None else f"{row[key]:.2f}"

    base_ms = {r["R"]: r["train_step_ms"] for r in rows if r["variant"] == "contracted"}
    for row in rows:
        cells = row["cells"]

        lines.append(
            f"| {row['R']:g} | {row['variant']} | {cells} | {row['train_step_ms']:.0f} "
            f"({row['train_step_ms'] / base_ms.get(row['R'], row['train_step_ms']):.2f}x) | "
            f"{row['train_memory_mib']:.0f} | {row['latency_ms']:.0f} | {num(row, 'RayIoU')} | {num(row, 'RayIoU_geometry')} | "
            f"{num(row, 'mIoU')} | {num(row, 'IoU')} |"
        )
    print("\n".join(lines))
    Path(args.out).mkdir(parents=True, exist_ok=True)
    (Path(args.out) / "table.json").write_text(json.dumps({"args": vars(args), "rows": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
