"""DuOcc's component ablation (paper Tab. 4) on the synthetic world: A, B, C, D and D evaluated with GT boxes.

Also B with the public code's concat fusion (``duocc/stream_agg_concat``) and, by ``--rows``, Tab. 5's StreamAgg
component rows and D with the auxiliary mask decoder (``full_mask``, which predicts as D does).

Each row is one shipped config (``duocc/<name>``) trained per seed in its own ``occplug fit`` process on the same
budget and evaluated on the validation split (camera mask), printed as mean ± std over the seeds:

* mIoU, static mIoU and dynamic mIoU: ``occ3d_miou``'s ``mIoU`` / ``mIoU_static`` / ``mIoU_dynamic`` over the core's
  class groups (``occplug.data.classes.OCC3D_STATIC`` / ``OCC3D_DYNAMIC``), the geometric IoU, and the IoU of car
  and pedestrian (car: the dynamic class with the most voxels);
* the detector's mAP (C, D, D with GT boxes, D with the mask decoder):
  :func:`occplug_duocc.tools.detection_eval.detection_map` (nuScenes-style, BEV centre distance 0.5 / 1 / 2 / 4 m) over the
  validation split read in order, the stream state carried as in evaluation, top 100 (query, class) pairs per frame;
* latency (ms per frame) and peak memory (MiB) of inference: the seed-0 run directories measured side by side by
  :func:`occplug.run.bench.run_bench` (each in its own process, interleaved; on CPU the memory is the process's peak
  RSS, so compare rows, not absolute values).

"D + GT boxes" is not trained: it is D's checkpoint evaluated with ``model.scene.query_agg.gt_boxes=true`` (what
``duocc/full_gt_boxes`` sets), through ``occplug validate``; its detector is D's, so its mAP equals D's.
The expected direction (paper: B > A; D > B with the gain mostly on dynamic classes) is printed as a check, not
tuned for::

    python -m occplug_duocc.tools.ablate                                   # 3 seeds, Tab. 4's rows, default world
    python -m occplug_duocc.tools.ablate --rows single_frame stream_warp_only stream_refine stream_refine_forecast stream_agg
    python -m occplug_duocc.tools.ablate --rows stream_agg full --seeds 0 1 2
    python -m occplug_duocc.tools.ablate --seeds 0 --preset tiny --epochs 1 --set trainer.max_steps=4   # a smoke run

Results go to ``--out`` (default ``runs/duocc_ablate``): one run directory per row and seed, and ``table.json``.
A finished run directory (its ``metrics.json``) is reused, so an interrupted ablation continues where it stopped;
one whose saved config differs from what the recipe and ``--set`` compose now stops the ablation (a fresh ``--out``).
``--eval-set`` re-scores every trained run with evaluation-only overrides (e.g. a score-threshold sweep of the
selection DQA uses: ``--eval-set model.scene.query_agg.score_threshold=0.5``), cached beside each run.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

from occplug.run.bench import evaluate_in_process, fit_in_process, mean_std, write_table_seeds

#: row -> (config stem trained, table label). ``full_gt_boxes`` evaluates ``full``'s runs.
ROWS = {
    "single_frame": ("single_frame", "A. Base (single frame)"),
    "stream_agg": ("stream_agg", "B. A + StreamAgg"),
    "stream_agg_concat": ("stream_agg_concat", "B, concat fusion (public code)"),
    "stream_agg_oracle_history": ("stream_agg_oracle_history", "B concat, oracle history (ground truth stored)"),
    "det_only": ("det_only", "C. B + detection head"),
    "full": ("full", "D. B + QueryAgg"),
    "full_gt_boxes": ("full", "D with GT boxes (eval only)"),
    "full_gt_trained": ("full_gt_trained", "D trained and evaluated with GT boxes"),
    "footprint_gt_boxes": ("footprint_gt_boxes", "B + GT-box class footprints (the oracle's control)"),
    "constant_gt_boxes": ("constant_gt_boxes", "D, GT boxes writing one constant embedding (the oracle's control)"),
    "noisy_gt_boxes": ("noisy_gt_boxes", "D trained and evaluated with GT boxes, centres moved by 2.4 m (x, y)"),
    "detector_pretrain": ("detector_pretrain", "D from a detection-only phase (its encoder and detector)"),
    "code_recipe": ("code_recipe", "D, the public code's recipe (concat, aabb, EMA, constant lr, its loss weights)"),
    "full_mask": ("full_mask", "D + mask decoder (training only)"),
    # Tab. 5: StreamAgg's components, one at a time (the last row, + occupied mask, is B)
    "stream_warp_only": ("stream_warp_only", "Tab. 5: warping only"),
    "stream_refine": ("stream_refine", "Tab. 5: + RefineNet"),
    "stream_refine_forecast": ("stream_refine_forecast", "Tab. 5: + forecasting"),
}
#: the rows run by default: Tab. 4 and the public code's fusion
DEFAULT_ROWS = ["single_frame", "stream_agg", "stream_agg_concat", "det_only", "full", "full_gt_boxes"]
COLUMNS = {
    "mIoU": "mIoU",
    "mIoU_D": "mIoU_dynamic",
    "mIoU_S": "mIoU_static",
    "IoU": "IoU",
    "car": "IoU_car",  # the most frequent dynamic class
    "ped.": "IoU_pedestrian",
}
DETECTOR_ROWS = (
    "det_only",
    "full",
    "full_gt_boxes",
    "full_mask",
    "full_gt_trained",
    "footprint_gt_boxes",
    "constant_gt_boxes",
    "noisy_gt_boxes",
    "detector_pretrain",
    "code_recipe",
)
GT_OVERRIDE = "model.scene.query_agg.gt_boxes=true"


def fit(config: str, seed: int, args: argparse.Namespace) -> Path:
    """The run directory of ``config`` at ``seed`` (trained first unless a finished one is there)."""
    out = Path(args.out) / f"{config}-seed{seed}"
    overrides = [
        f"seed={seed}",
        "trainer.enable_progress_bar=false",
        f"data.preset={args.preset}",
        f"trainer.max_epochs={args.epochs}",
        *args.set,
    ]
    if (out / "config.yaml").is_file():  # reuse (or resume) only a run of the config the recipe composes today
        from occplug.run import runner

        today = runner.saved_run_config(runner.load_config([f"duocc/{config}"], overrides))
        if runner.read_run_config(out / "config.yaml") != today:
            print(
                f"error: {out} was trained with another config than duocc/{config} {' '.join(overrides)} composes "
                "now (a recipe or --set changed); choose a fresh --out",
                file=sys.stderr,
            )
            raise SystemExit(2)
    if (out / "metrics.json").is_file():
        return out
    return fit_in_process(f"duocc/{config}", overrides, out, f"{config} seed {seed}")


def gt_metrics(run: Path) -> dict:
    """Metrics of ``run``'s checkpoint validated with ground-truth boxes in DQA (cached beside the run)."""
    return evaluate_in_process(final_run(run), "val", [GT_OVERRIDE], name="metrics_gt_boxes")


def final_run(run: Path) -> Path:
    """``run``, or for a run of phases its last phase's folder (the model the row evaluates)."""
    if not (run / "checkpoints").is_dir() and (run / "metrics.json").is_file():
        phases = list(json.loads((run / "metrics.json").read_text()).get("phases") or [])
        if phases:
            return run / phases[-1]
    return run


def checkpoint(run: Path) -> Path:
    """The run's last checkpoint (a run of phases: its last phase's)."""
    run = final_run(run)
    last = run / "checkpoints" / "last.ckpt"
    if last.is_file():
        return last
    found = sorted((run / "checkpoints").glob("*.ckpt"))
    if not found:
        raise SystemExit(f"{run}: no checkpoint to evaluate")
    return found[-1]


def detection_map_of(run: Path, gt_boxes: bool) -> float:
    """The detector's mAP (percent) on the validation split, frames in order (cached beside the run)."""
    path = run / ("det_map_gt_boxes.json" if gt_boxes else "det_map.json")
    if path.is_file():
        return float(json.loads(path.read_text())["mAP"])
    import yaml

    from occplug.run import runner

    from .detection_eval import stream_detection_map

    saved = yaml.safe_load((final_run(run) / "config.yaml").read_text())
    cfg = runner.load_config([], [GT_OVERRIDE] if gt_boxes else [], saved=saved)
    dm, model = runner.build_run(cfg)
    model.load_state_dict(runner.load_checkpoint(checkpoint(run))["state_dict"])
    dm.prepare_data()
    dm.setup("validate")
    result = stream_detection_map(model, dm.val_dataloader(), "val")
    value = 100.0 * float(result["mAP"])
    path.write_text(json.dumps({"mAP": value, "AP": result["AP"]}, indent=2) + "\n")
    return value


def mean(values: list[float]) -> float:
    values = [v for v in values if v == v]
    return statistics.mean(values) if values else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(
        prog="python -m occplug_duocc.tools.ablate",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--rows", nargs="+", default=DEFAULT_ROWS, choices=list(ROWS))
    parser.add_argument("--epochs", type=int, default=8, help="trainer.max_epochs of every run (the CPU budget)")
    parser.add_argument("--preset", default="default", help="synthetic world preset (default: default)")
    parser.add_argument("--set", nargs="*", default=[], help="extra key=value overrides for every run")
    parser.add_argument("--repeats", type=int, default=5, help="latency / training rounds of the benchmark")
    parser.add_argument("--device", default="cpu", help="benchmark device: cpu | cuda | auto")
    parser.add_argument("--no-bench", action="store_true", help="skip latency and memory")
    parser.add_argument("--out", default="runs/duocc_ablate")
    parser.add_argument(
        "--eval-set",
        nargs="*",
        default=[],
        help="evaluation-only key=value overrides, e.g. model.scene.query_agg.score_threshold=0.5: each trained run "
        "is re-scored on the validation split (cached beside it), nothing is retrained",
    )
    parser.add_argument(
        "--results",
        help="also write each row's numbers per seed as small JSONs here (commit them under results/duocc/<claim>/)",
    )
    args = parser.parse_args()
    start = time.monotonic()
    table: dict[str, dict[str, list[float]]] = {}
    runs: dict[str, Path] = {}
    for row in args.rows:  # row by row: an interrupted ablation leaves whole rows
        config, _ = ROWS[row]
        cells = table.setdefault(row, {**{c: [] for c in COLUMNS}, "mAP": []})
        for seed in args.seeds:
            run = fit(config, seed, args)
            runs.setdefault(row, run)
            if args.eval_set:  # re-scored with evaluation-only overrides (cached beside the run)
                gt = [GT_OVERRIDE] if row == "full_gt_boxes" else []
                metrics = evaluate_in_process(final_run(run), "val", [*gt, *args.eval_set])
            elif row == "full_gt_boxes":
                metrics = gt_metrics(run)
            else:
                metrics = json.loads((run / "metrics.json").read_text())
            for column, key in COLUMNS.items():
                value = metrics.get(key)  # None: a class absent from both ground truth and prediction
                cells[column].append(float("nan") if value is None else float(value))
            if row in DETECTOR_ROWS:
                cells["mAP"].append(detection_map_of(run, row == "full_gt_boxes"))
    bench: dict[str, tuple[float, float]] = {}
    header = ""
    if not args.no_bench and runs:
        from occplug.run.bench import BenchSettings, resolve_target, run_bench

        settings = BenchSettings(
            repeats=args.repeats, warmup=1, train_repeats=args.repeats, batch_size=1, device=args.device
        )
        targets = [
            resolve_target(str(run), settings, [GT_OVERRIDE] if row == "full_gt_boxes" else [])
            for row, run in runs.items()
        ]
        report = run_bench(targets, settings, progress=lambda line: print(line, file=sys.stderr))
        bench = {row: (r.latency_ms, r.memory_mib) for row, r in zip(runs, report.rows, strict=True)}
        header = f"{report.machine}; {report.device}; "
    lines = [
        f"{header}seeds {args.seeds}, world '{args.preset}', {args.epochs} epochs per run, "
        f"{time.monotonic() - start:.0f} s",
        "",
        "| method | mIoU | mIoU_D (dynamic) | mIoU_S (static) | IoU | car IoU | ped. IoU | det mAP | latency (ms) "
        "| peak mem (MiB) |",
        "|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|",
    ]
    for row, cells in table.items():
        lat, mem = bench.get(row, (float("nan"), float("nan")))
        lines.append(
            f"| {ROWS[row][1]} | "
            + " | ".join(mean_std(cells[c]) for c in COLUMNS)
            + f" | {mean_std(cells['mAP'])} | "
            + ("—" if lat != lat else f"{lat:.1f}")
            + " | "
            + ("—" if mem != mem else f"{mem:.0f}")
            + " |"
        )
    a, b, d = (table.get(k) for k in ("single_frame", "stream_agg", "full"))
    lines.append("")
    if a and b:
        ma, mb = mean(a["mIoU"]), mean(b["mIoU"])
        lines.append(f"B > A (mIoU {mb:.2f} vs {ma:.2f}; paper 40.4 vs 36.8): {'PASS' if mb > ma else 'FAIL'}")
    if a and table.get("stream_agg_concat"):
        ma, mc = mean(a["mIoU"]), mean(table["stream_agg_concat"]["mIoU"])
        lines.append(f"B (concat fusion) > A (mIoU {mc:.2f} vs {ma:.2f}): {'PASS' if mc > ma else 'FAIL'}")
    if b and d:
        gain = mean(d["mIoU"]) - mean(b["mIoU"])
        dyn, sta = mean(d["mIoU_D"]) - mean(b["mIoU_D"]), mean(d["mIoU_S"]) - mean(b["mIoU_S"])
        lines.append(f"D > B (mIoU gain {gain:+.2f}; paper +1.5): {'PASS' if gain > 0 else 'FAIL'}")
        lines.append(
            f"D's gain mostly dynamic (dynamic {dyn:+.2f} vs static {sta:+.2f}; paper +2.7 vs -0.1): "
            f"{'PASS' if dyn > sta and dyn > 0 else 'FAIL'}"
        )
    print("\n".join(lines))
    Path(args.out).mkdir(parents=True, exist_ok=True)
    (Path(args.out) / "table.json").write_text(
        json.dumps({"args": vars(args), "rows": table, "bench": bench}, indent=2) + "\n"
    )
    if args.results:
        settings = {"epochs": args.epochs, "preset": args.preset, "set": args.set}
        if args.eval_set:
            settings["eval_set"] = args.eval_set
        write_table_seeds(args.results, table, args.seeds, settings)


if __name__ == "__main__":
    main()
