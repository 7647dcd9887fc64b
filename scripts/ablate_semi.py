"""Label-efficient training of the baseline: full labels vs 10 % teacher only vs 10 % teacher -> student -> finetune.

Runs ``configs/semi/baseline_100pct.yaml`` and ``configs/semi/baseline_10pct.yaml`` per seed (the 10 % run's
``teacher`` phase *is* ``baseline_10pct_teacher_only.yaml``: same config, same seed, so it is read from there
instead of trained twice), each in its own ``occplug fit`` process, and prints mean ± std over the seeds of
mIoU and IoU (validation split, camera mask) and the share of the full-label mIoU each recovers::

    python scripts/ablate_semi.py                       # 3 seeds, the recipes' epochs, default world
    python scripts/ablate_semi.py --epochs 0.5          # every phase's epochs halved (a CPU budget)
    python scripts/ablate_semi.py --seeds 0 --preset tiny --epochs 0.1   # a smoke run

Results go to ``--out`` (default ``runs/ablate_semi``): one run directory per recipe and seed, and
``table.json``. A finished run directory is reused, so an interrupted ablation continues where it stopped.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from pathlib import Path

from occplug.run.bench import fit_in_process, mean_std

ROOT = Path(__file__).resolve().parents[1]
RECIPES = {"full": ROOT / "configs/semi/baseline_100pct.yaml", "semi": ROOT / "configs/semi/baseline_10pct.yaml"}


def phase_epochs(recipe: Path) -> dict[str, int]:
    """``{phase: trainer.max_epochs}`` of a recipe (the run's own epochs where a phase sets none)."""
    from occplug.config import phase_specs
    from occplug.run.runner import load_config

    cfg = load_config([str(recipe)])
    return {s.name: int(s.config["trainer"]["max_epochs"]) for s in phase_specs(cfg)}


def run(recipe: str, seed: int, args: argparse.Namespace) -> dict:
    """The run's metrics.json (training it first unless a finished one is there)."""
    out = Path(args.out) / f"{recipe}-seed{seed}"
    if (out / "metrics.json").is_file():
        summary = json.loads((out / "metrics.json").read_text())
        if set(summary.get("phases", {})) == set(phase_epochs(RECIPES[recipe])):
            return summary
    overrides = [f"seed={seed}", "trainer.enable_progress_bar=false", f"data.preset={args.preset}"]
    for phase, epochs in phase_epochs(RECIPES[recipe]).items():
        overrides.append(f"phases.{phase}.trainer.max_epochs={max(1, round(epochs * args.epochs))}")
    fit_in_process(str(RECIPES[recipe]), overrides, out, f"{recipe} seed {seed}")
    return json.loads((out / "metrics.json").read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--epochs", type=float, default=1.0, help="scale every phase's max_epochs (a CPU budget)")
    parser.add_argument("--preset", default="default", help="synthetic world preset (default: default)")
    parser.add_argument("--out", default="runs/ablate_semi")
    args = parser.parse_args()
    start = time.monotonic()
    rows: dict[str, dict[str, list[float]]] = {}

    def add(name: str, metrics: dict) -> None:
        row = rows.setdefault(name, {"mIoU": [], "IoU": []})
        row["mIoU"].append(float(metrics["mIoU"]))
        row["IoU"].append(float(metrics["IoU"]))

    for seed in args.seeds:
        full = run("full", seed, args)
        semi = run("semi", seed, args)
        add("100 % labels", full)
        add("10 % labels, teacher only", semi["phases"]["teacher"])
        add("10 %: + student (pseudo labels)", semi["phases"]["student"])
        add("10 %: + student + finetune", semi["phases"]["finetune"])
    reference = statistics.mean(rows["100 % labels"]["mIoU"])
    lines = [
        f"seeds {args.seeds}, world '{args.preset}', epochs x{args.epochs:g}, {time.monotonic() - start:.0f} s",
        "",
        "| training | mIoU | IoU | share of full-label mIoU |",
        "|---|--:|--:|--:|",
    ]
    for name, row in rows.items():
        share = statistics.mean(row["mIoU"]) / reference * 100 if reference > 0 else math.nan
        lines.append(f"| {name} | {mean_std(row['mIoU'])} | {mean_std(row['IoU'])} | {share:.0f} % |")
    print("\n".join(lines))
    Path(args.out).mkdir(parents=True, exist_ok=True)
    (Path(args.out) / "table.json").write_text(json.dumps({"args": vars(args), "rows": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
