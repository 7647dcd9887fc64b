"""DuOcc's streaming against dense multi-frame stacking: per-frame time, memory and accuracy (paper Fig. 1, Tab. 1).

Rows: ``duocc/stream_agg`` (StreamAgg: one warped history, whatever the horizon; Eq. 5's sum), ``duocc/stream_agg_concat``
(the same with the public code's bounded concat fusion: on the synthetic world the sum's history grows along the
stream, see the README) and ``duocc/stacking`` with
``num_history = K`` past frames (``K = 1, 2, 4, 8``: K warped ``V_curr`` concatenated with the current one, the
dense multi-frame fusion of Fig. 1 a). Same view transform, 3D-FPN, decoder and losses otherwise.

Time and memory: every row goes through :func:`occplug.run.bench.run_bench` together -- each model in its own process,
interleaved round by round, so the rows are measured side by side. Per-frame latency is inference at batch 1
(median; the stacking rows fuse K + 1 volumes per frame, the stream one history); memory is the inference peak
(CUDA's peak allocation on a GPU, else the process's peak RSS on CPU, which includes the data and the
interpreter: compare rows, not absolute values); the training step (batch 1, data loading excluded) is reported
too. Accuracy: with ``--epochs N`` each row is trained first (``occplug fit``, once per seed of ``--seeds``, each
in its own process) and the mIoU column is the mean ± std of the runs' ``metrics.json`` (camera mask); time and memory
are measured on the first seed's run directories. With ``--epochs 0`` the configs are measured untrained (no
accuracy). A finished run directory is reused, so seeds can be trained by separate invocations side by side and
tabled by a last one over all of them::

    python -m occplug_duocc.tools.bench                                       # K = 1 2 4 8, default world, 4 epochs, seed 0
    python -m occplug_duocc.tools.bench --seeds 0 1 2                         # accuracy as mean ± std over 3 seeds
    python -m occplug_duocc.tools.bench --preset tiny --epochs 1 --set trainer.max_steps=4 --repeats 2 --train-repeats 2
    python -m occplug_duocc.tools.bench --device cuda --preset occ3d --epochs 0 --full --repeats 10 --train-repeats 0 \\
        --set "grid={range: [-40.0, -40.0, -1.0, 40.0, 40.0, 5.4], voxel_size: 0.4}"

``--train-repeats 0`` measures inference only: a training step on the ``occ3d`` world reads frames the benchmark
has not generated yet (about 4 s each on one CPU core, K + 1 of them per stacking sample), so its training rounds
take many minutes.

GPU note: the paper measures 256 x 704 images, a 200 x 200 x 16 grid (0.4 m) and a ResNet-50 on an A100 --
83.3 ms and 2,788 MB for the full DuOcc, 49.0 ms / 2,437 MB for StreamAgg only (Tab. 1, Tab. 7). The ``occ3d``
preset has those images and that grid (the ``grid`` override above puts the model on it; the recipes' small CNN and
32-channel volumes stay, so expect far lower absolute numbers: compare the rows' ratios, not the paper's values).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from occplug.run.bench import fit_in_process, mean_std


def rows(ks: list[int], full: bool = False) -> list[tuple[str, str, list[str]]]:
    """``(name, config, overrides)`` of every row (``full``: the whole DuOcc, D, last)."""
    out = [("stream_agg", "duocc/stream_agg", []), ("stream_agg_concat", "duocc/stream_agg_concat", [])]
    out += [(f"stacking_K{k}", "duocc/stacking", [f"model.scene.num_history={k}"]) for k in ks]
    return out + ([("full", "duocc/full", [])] if full else [])


def _num(value: float | None) -> str:
    return "—" if value is None else f"{value:.0f}"


def common(args: argparse.Namespace) -> list[str]:
    return [f"data.preset={args.preset}", *args.set]


def train(name: str, config: str, overrides: list[str], seed: int, args: argparse.Namespace) -> Path:
    """The run directory of a row at ``seed`` (trained first unless a finished one is there)."""
    out = Path(args.out) / f"{name}-seed{seed}"
    if (out / "metrics.json").is_file():
        return out
    run_overrides = [
        f"seed={seed}",
        "trainer.enable_progress_bar=false",
        f"trainer.max_epochs={args.epochs}",
        *common(args),
        *overrides,
    ]
    return fit_in_process(config, run_overrides, out, f"{name}, seed {seed}")


def main() -> None:
    parser = argparse.ArgumentParser(
        prog="python -m occplug_duocc.tools.bench",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--ks", type=int, nargs="+", default=[1, 2, 4, 8], help="past frames K of the stacking rows")
    parser.add_argument("--epochs", type=int, default=4, help="training epochs per row (0: measure untrained)")
    parser.add_argument(
        "--seeds", type=int, nargs="+", default=[0], help="training seeds (accuracy: mean ± std; timing: the first)"
    )
    parser.add_argument("--preset", default="default", help="synthetic world preset (default: default)")
    parser.add_argument("--set", nargs="*", default=[], help="extra key=value overrides for every row")
    parser.add_argument("--repeats", type=int, default=5, help="latency rounds per model")
    parser.add_argument("--device", default="cpu", help="cpu | cuda | auto")
    parser.add_argument(
        "--train-repeats", type=int, default=5, help="timed training steps per model (0: inference only)"
    )
    parser.add_argument("--full", action="store_true", help="add the full DuOcc (D, duocc/full) as a last row")
    parser.add_argument("--out", default="runs/duocc_bench")
    args = parser.parse_args()
    if args.train_repeats < 0:
        parser.error(f"--train-repeats: expected an int >= 0 (0: inference only), got {args.train_repeats}")
    if args.epochs == 0 and args.seeds != [0]:
        parser.error("--seeds: untrained rows (--epochs 0) have no seeds to average; leave --seeds out")
    if len(set(args.seeds)) != len(args.seeds):
        parser.error(f"--seeds: each seed once, got {args.seeds}")

    from occplug.run.bench import BenchSettings, read_accuracy, resolve_target, run_bench

    settings = BenchSettings(
        repeats=args.repeats, warmup=1, train_repeats=args.train_repeats, batch_size=1, device=args.device
    )
    start = time.monotonic()
    targets, mious = [], []
    for name, config, overrides in rows(args.ks, args.full):
        if args.epochs > 0:
            runs = [train(name, config, overrides, seed, args) for seed in args.seeds]
            values = [read_accuracy(json.loads((run / "metrics.json").read_text()))["mIoU"] for run in runs]
            mious.append([v for v in values if v is not None])
            targets.append(resolve_target(str(runs[0]), settings))
        else:
            target = resolve_target(config, settings, [*common(args), *overrides])
            target.name = name
            targets.append(target)
            mious.append([])
    report = run_bench(targets, settings, progress=lambda line: print(line, file=sys.stderr))
    names = [name for name, _, _ in rows(args.ks, args.full)]
    base = report.rows[0]
    lines = [
        f"{report.machine}; {report.device}; torch {report.versions.get('torch', '?')}; world '{args.preset}'; "
        f"{'untrained' if args.epochs == 0 else f'{args.epochs} epochs, seeds {args.seeds} (timed: the first)'}; "
        f"{time.monotonic() - start:.0f} s",
        "",
        "| model | frames fused | params | latency / frame (ms) | inference peak (MiB) | train step (ms) | "
        "train peak (MiB) | mIoU |",
        "|---|--:|--:|--:|--:|--:|--:|--:|",
    ]
    table = []
    for name, row, values in zip(names, report.rows, mious, strict=True):
        frames = str(int(name.split("K")[1]) + 1) if name.startswith("stacking") else "stream"
        miou = mean_std(values)
        lines.append(
            f"| {name} | {frames} | {row.params} | {row.latency_ms:.1f} ({row.latency_ms / base.latency_ms:.2f}x) | "
            f"{row.memory_mib:.0f} | {_num(row.train_step_ms)} | {_num(row.train_memory_mib)} | {miou} |"
        )
        table.append(
            {
                "model": name,
                **{
                    k: getattr(row, k)
                    for k in ("params", "latency_ms", "memory_mib", "train_step_ms", "train_memory_mib")
                },
                "mIoU": values,
            }
        )
    lines += [
        "",
        "paper (A100, 256 x 704, 200 x 200 x 16, ResNet-50): DuOcc 83.3 ms / 2,788 MB; StreamAgg only 49.0 ms / "
        "2,437 MB; dense multi-frame methods 213-1,250 ms / 5-12 GB",
    ]
    print("\n".join(lines))
    Path(args.out).mkdir(parents=True, exist_ok=True)
    (Path(args.out) / "table.json").write_text(json.dumps({"args": vars(args), "rows": table}, indent=2) + "\n")


if __name__ == "__main__":
    main()
