"""Three cross-method mixes (``configs/mix/``) against their parents, all re-measured in the same run (issue 43).

Each row is a config (a plugin's recipe, a mix, or a recipe with one override) trained per seed in its own
``occplug fit`` process and scored on the validation split (camera mask), printed per mix as mean ± std over the
seeds in the columns its parents report:

* **label-free streaming** (QueryOcc's budget, 4 epochs; QueryOcc's columns: Sem./Occ. RayIoU, Sem./Occ. IoU):
  ``queryocc/base`` (its contracted BEV field), ``configs/mix/label_free_stream.yaml`` (its queries on DuOcc's
  stream, T = {-1, 0, 1}) and ``configs/mix/label_free_stream_t0.yaml`` (T = {0});
* **label-efficient streaming** (DuOcc's budget, 8 epochs per phase-equivalent; DuOcc's columns: mIoU, dynamic,
  static, IoU): DuOcc B (``duocc/stream_agg_concat``) at 100 % and at 10 % labels (``data.label_fraction=0.1``),
  B at 10 % for the recipe's 20 epochs (more training alone) and ``configs/mix/duocc_b_three_phase_10pct.yaml``;
* **queries at 10 %** (DuOcc's budget): B at 100 % and 10 %, and ``configs/mix/duocc_b_10pct_queries.yaml``.

A row two mixes share (B at 100 % and at 10 %) trains once per seed. Under each table one line per mix row gives its
difference to each parent row and on how many seeds it is ahead; nothing is judged PASS / FAIL::

    python scripts/ablate_mix.py                               # every mix, 3 seeds, the parents' budgets
    python scripts/ablate_mix.py --rows label_free_stream queryocc_base --seeds 0 1 2
    python scripts/ablate_mix.py --dry-run                     # the planned runs and their epochs
    python scripts/ablate_mix.py --seeds 0 --preset tiny --epochs 0.25   # a smoke run

``--epochs`` scales every row's budget (1 = the parents' own ablation budgets: ``python -m occplug_queryocc.tools.ablate``
trains 4 epochs, ``python -m occplug_duocc.tools.ablate`` 8; a phased row scales each phase's epochs), at least 1 epoch
each. ``--set`` adds overrides to every run (one under ``phases.<name>.`` only to the rows that declare that phase).
``--split test`` scores every trained run on the test split instead (cached beside the run, nothing retrained).
Results go to ``--out`` (default ``runs/ablate_mix``): one run directory per row and seed, and ``table.json``;
``--results DIR`` also writes one small JSON per row and seed. A finished run directory is reused, so an
interrupted ablation continues where it stopped.

CPU budget, measured (``results/mix/RESULTS.md``): the 24 runs of 3 seeds took 2 h 12 min of wall time on a 2-core
CPU, three to five runs side by side with one thread each (DuOcc B, 8 epochs: 8-11 min per run; the three-phase
row 27 min; QueryOcc base 13-20 min).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import NamedTuple

from occplug.run.bench import evaluate_in_process, fit_in_process, mean_std, write_seed_result

ROOT = Path(__file__).resolve().parents[1]
MIX = ROOT / "configs" / "mix"
#: The parents' own ablation budgets (epochs per run).
QUERYOCC_EPOCHS, DUOCC_EPOCHS = 4, 8


class Row(NamedTuple):
    """One row: the config trained, its own overrides, its label and its budget (a phased row: its phases')."""

    config: str
    label: str
    epochs: int | None  # None: the phased config's own per-phase epochs
    overrides: tuple[str, ...] = ()


ROWS = {
    "queryocc_base": Row("queryocc/base", "QueryOcc (contracted BEV), T = {-1, 0, 1}", QUERYOCC_EPOCHS),
    "label_free_stream": Row(
        str(MIX / "label_free_stream.yaml"), "mix: QueryOcc queries on DuOcc's stream, T = {-1, 0, 1}", QUERYOCC_EPOCHS
    ),
    "label_free_stream_t0": Row(
        str(MIX / "label_free_stream_t0.yaml"), "mix: QueryOcc queries on DuOcc's stream, T = {0}", QUERYOCC_EPOCHS
    ),
    "duocc_b_100pct": Row("duocc/stream_agg_concat", "DuOcc B (concat), 100 % labels", DUOCC_EPOCHS),
    "duocc_b_10pct": Row(
        "duocc/stream_agg_concat", "DuOcc B (concat), 10 % labels", DUOCC_EPOCHS, ("data.label_fraction=0.1",)
    ),
    "duocc_b_10pct_20ep": Row(
        "duocc/stream_agg_concat",
        "DuOcc B (concat), 10 % labels, the recipe's 20 epochs",
        20,  # the three-phase recipe's 8 + 8 + 4
        ("data.label_fraction=0.1",),
    ),
    "duocc_b_three_phase_10pct": Row(
        str(MIX / "duocc_b_three_phase_10pct.yaml"), "mix: DuOcc B, OccLE's teacher -> student -> finetune, 10 %", None
    ),
    "duocc_b_10pct_queries": Row(
        str(MIX / "duocc_b_10pct_queries.yaml"), "mix: DuOcc B, 10 % labels + QueryOcc's queries", DUOCC_EPOCHS
    ),
}
#: Each mix: its question, the columns its parents report (column -> metrics.json key), its rows (mix rows last).
MIXES = {
    "label-free streaming": {
        "question": "does a stream make label-free learning better, and does T = {-1, 0, 1} pay on a stream?",
        "columns": {"Sem.RayIoU": "RayIoU", "Occ.RayIoU": "RayIoU_geometry", "Sem.IoU": "mIoU", "Occ.IoU": "IoU"},
        "parents": ["queryocc_base"],
        "mixes": ["label_free_stream", "label_free_stream_t0"],
    },
    "label-efficient streaming": {
        "question": "does OccLE's label-efficiency recipe carry over to a camera-only streaming model?",
        "columns": {"mIoU": "mIoU", "mIoU_D": "mIoU_dynamic", "mIoU_S": "mIoU_static", "IoU": "IoU"},
        "parents": ["duocc_b_100pct", "duocc_b_10pct", "duocc_b_10pct_20ep"],
        "mixes": ["duocc_b_three_phase_10pct"],
    },
    "queries at 10 % labels": {
        "question": "do QueryOcc's label-free queries pay on the 90 % of frames without voxel labels?",
        "columns": {"mIoU": "mIoU", "mIoU_D": "mIoU_dynamic", "mIoU_S": "mIoU_static", "IoU": "IoU"},
        "parents": ["duocc_b_100pct", "duocc_b_10pct"],
        "mixes": ["duocc_b_10pct_queries"],
    },
}


def phase_budget(row: Row) -> dict[str, int]:
    """``{phase: max_epochs}`` of a phased row's config."""
    from occplug.config import phase_specs
    from occplug.run.runner import load_config

    return {s.name: int(s.config["trainer"]["max_epochs"]) for s in phase_specs(load_config([row.config]))}


def overrides(name: str, seed: int, args: argparse.Namespace) -> list[str]:
    """The command-line overrides of ``name``'s run at ``seed``: the row's own, the scaled budget, ``--set``."""
    row = ROWS[name]
    out = [f"seed={seed}", "trainer.enable_progress_bar=false", f"data.preset={args.preset}", *row.overrides]
    phases = phase_budget(row) if row.epochs is None else {}
    if phases:
        out += [f"phases.{p}.trainer.max_epochs={max(1, round(e * args.epochs))}" for p, e in phases.items()]
    else:
        out.append(f"trainer.max_epochs={max(1, round(row.epochs * args.epochs))}")
    for item in args.set:
        key = item.split("=", 1)[0].lstrip("~").split(".")
        if key[0] != "phases" or (len(key) > 1 and key[1] in phases):
            out.append(item)
    return out


def final_run(run: Path) -> Path:
    """``run``, or for a run of phases its last phase's folder (the model the row scores)."""
    summary = json.loads((run / "metrics.json").read_text())
    return run / summary["final_phase"] if summary.get("final_phase") else run


def measure(name: str, seed: int, args: argparse.Namespace) -> dict:
    """The row's metrics at ``seed`` on ``args.split`` (trained first unless a finished run is there)."""
    out = Path(args.out) / f"{name}-seed{seed}"
    wanted = overrides(name, seed, args)
    record = out / "ablate_mix_overrides.json"  # what the run in this folder was trained with
    if record.is_file() and json.loads(record.read_text()) != [ROWS[name].config, *wanted]:
        print(
            f"error: {out} was trained with other settings than this command's (--epochs, --preset or --set changed); "
            "choose a fresh --out",
            file=sys.stderr,
        )
        raise SystemExit(2)
    if not (out / "metrics.json").is_file():
        fit_in_process(ROWS[name].config, wanted, out, f"{name} seed {seed}")
        record.write_text(json.dumps([ROWS[name].config, *wanted]) + "\n")
    if args.split == "val":
        return json.loads((out / "metrics.json").read_text())
    return evaluate_in_process(final_run(out), args.split)


def value(metrics: dict, key: str) -> float:
    """``metrics[key]`` as a float; NaN where it is missing or null (a class absent from truth and prediction)."""
    v = metrics.get(key)
    return float("nan") if v is None else float(v)


def differences(table: dict[str, dict[str, list[float]]], mix: dict, column: str) -> list[str]:
    """One line per mix row and each parent row (and each mix row before it): the mean difference in ``column`` (the
    parents' headline: QueryOcc's Sem.RayIoU, DuOcc's mIoU) and on how many seeds the mix row leads."""
    lines = []
    for i, m in enumerate(mix["mixes"]):
        for p in (r for r in [*mix["parents"], *mix["mixes"][:i]] if r in table and m in table):
            a, b = table[m][column], table[p][column]
            pairs = [(x, y) for x, y in zip(a, b, strict=True) if x == x and y == y]
            if not pairs:
                continue
            diff = statistics.mean(x for x, _ in pairs) - statistics.mean(y for _, y in pairs)
            ahead = sum(x > y for x, y in pairs)
            lines.append(f"{m} - {p} ({column}): {diff:+.2f}, ahead on {ahead} of {len(pairs)} seeds")
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python scripts/ablate_mix.py", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument(
        "--epochs", type=float, default=1.0, help="scale every row's budget (1: the parents' ablation budgets)"
    )
    parser.add_argument("--preset", default="default", help="synthetic world preset (default: default)")
    parser.add_argument("--set", nargs="*", default=[], help="extra key=value overrides for every run")
    parser.add_argument("--split", default="val", choices=["val", "test"], help="the split scored (default val)")
    parser.add_argument("--out", default="runs/ablate_mix")
    parser.add_argument("--results", help="also write each row's numbers per seed as small JSONs here")
    parser.add_argument("--dry-run", action="store_true", help="print the planned runs and train nothing")
    args = parser.parse_args(argv)
    if args.dry_run:
        for name in args.rows:
            for seed in args.seeds:
                print(
                    f"{Path(args.out) / f'{name}-seed{seed}'}: -c {ROWS[name].config} {' '.join(overrides(name, seed, args))}"
                )
        return
    start = time.monotonic()
    metrics = {(name, seed): measure(name, seed, args) for name in args.rows for seed in args.seeds}
    lines = [
        f"seeds {args.seeds}, world '{args.preset}', epochs x {args.epochs:g}, {args.split} split, "
        f"{time.monotonic() - start:.0f} s"
    ]
    tables: dict[str, dict[str, dict[str, list[float]]]] = {}
    for title, mix in MIXES.items():
        names = [r for r in [*mix["parents"], *mix["mixes"]] if r in args.rows]
        if not any(r in mix["mixes"] for r in names):
            continue
        columns = mix["columns"]
        table = {r: {c: [value(metrics[r, s], k) for s in args.seeds] for c, k in columns.items()} for r in names}
        tables[title] = table
        lines += [
            "",
            f"### {title}: {mix['question']}",
            "",
            "| row | config | " + " | ".join(columns) + " |",
            "|---|---|" + "--:|" * len(columns),
        ]
        for r in names:
            lines.append(f"| {ROWS[r].label} | `{r}` | " + " | ".join(mean_std(v) for v in table[r].values()) + " |")
        lines += ["", *differences(table, mix, next(iter(columns)))]
    print("\n".join(lines))
    Path(args.out).mkdir(parents=True, exist_ok=True)
    (Path(args.out) / "table.json").write_text(json.dumps({"args": vars(args), "tables": tables}, indent=2) + "\n")
    if args.results:  # one file per row and seed (a row two mixes share: once), with the run's exact overrides
        rows = {r: cells for table in tables.values() for r, cells in table.items()}
        for r, cells in rows.items():
            for i, seed in enumerate(args.seeds):
                settings = {"config": ROWS[r].config, "overrides": overrides(r, seed, args), "split": args.split}
                write_seed_result(args.results, r, seed, {c: v[i] for c, v in cells.items()}, settings)


if __name__ == "__main__":
    main()
