#!/usr/bin/env python
"""Benchmark a short baseline training run on the synthetic world: steps/s, peak RSS, where a step's time goes.

Trains ``configs/baseline.yaml`` (the ``default`` synthetic world unless overridden) for
``--steps`` optimiser steps with no validation, checkpoints or logger, under Lightning's
:class:`~lightning.pytorch.profilers.SimpleProfiler`, and prints:

* steps/s over the steps after ``--warmup`` (wall-clock, data loading included);
* peak RSS: of the whole process, and the peak during training above the level before it
  (Linux ``VmHWM`` after a ``/proc/self/clear_refs`` reset);
* the share of the measured wall time spent waiting for data (``train_dataloader_next``: fetch +
  collate with ``num_workers`` as configured), in forward (``training_step``: model + losses),
  backward, and the optimiser (``optimizer_step`` minus the forward, zero_grad and backward that
  Lightning's closure runs inside it: gradient clipping + ``optimizer.step``; zero_grad is listed
  on its own), the rest being Lightning/logging overhead.

Frames are generated (and cached) before anything is timed. Extra ``key=value`` arguments
override the config, e.g. ``data.preset=tiny`` or ``model.view_transform.splat=reference``.

Usage: ``python scripts/bench_fit.py [--steps 50] [--warmup 5] [--threads N] [key=value ...]``
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.profilers import SimpleProfiler

from occplug.run import runner

ROOT = Path(__file__).resolve().parents[1]


class StepClock(Callback):
    """Wall-clock time at the end of every training batch."""

    def __init__(self) -> None:
        self.ends: list[float] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:  # type: ignore[override]
        self.ends.append(time.perf_counter())


def _status_kb(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return -1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-c", "--config", default=str(ROOT / "configs" / "baseline.yaml"))
    parser.add_argument("--steps", type=int, default=50, help="optimiser steps to run")
    parser.add_argument("--warmup", type=int, default=5, help="first steps left out of the numbers")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    parser.add_argument("overrides", nargs="*", metavar="key=value")
    args = parser.parse_args()
    if args.steps <= args.warmup:
        parser.error("--steps must exceed --warmup")
    if args.threads:
        torch.set_num_threads(args.threads)

    cfg = runner.load_config([args.config], args.overrides)
    L.seed_everything(int(cfg.get("seed", 0)), verbose=False)
    dm = runner.build_datamodule(cfg)
    print("preparing data (generated once, then cached) ...", flush=True)
    dm.prepare_data()
    model = runner.build_model(cfg, dm)

    trainer_args = dict(cfg.get("trainer") or {})
    trainer_args.update(
        max_steps=args.steps,
        max_epochs=-1,
        limit_val_batches=0,
        num_sanity_val_steps=0,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    clock = StepClock()
    with tempfile.TemporaryDirectory() as tmp:
        profiler = SimpleProfiler(dirpath=tmp, filename="profile")  # the report goes to a file, not stdout
        trainer = L.Trainer(profiler=profiler, callbacks=[clock], **trainer_args)
        try:
            Path("/proc/self/clear_refs").write_text("5")
        except OSError:
            pass
        rss_before = _status_kb("VmRSS")
        trainer.fit(model, datamodule=dm)
        rss_peak_fit = _status_kb("VmHWM")
        durations = {k: list(v) for k, v in profiler.recorded_durations.items()}

    def per_step(suffix: str) -> list[float]:
        matches = [v for k, v in durations.items() if k.endswith(suffix)]
        if not matches:
            raise KeyError(f"profiler recorded no '{suffix}' action; recorded: {sorted(durations)}")
        return matches[0][args.warmup : args.steps]

    steps = len(clock.ends) - args.warmup
    wall = clock.ends[-1] - clock.ends[args.warmup - 1] if args.warmup else clock.ends[-1] - clock.ends[0]
    if not args.warmup:
        steps -= 1  # the window starts at the end of the first step
    data = per_step("train_dataloader_next")
    forward = per_step(".training_step")
    backward = per_step(".backward")
    zero_grad = per_step(".optimizer_zero_grad")
    opt_total = per_step(".optimizer_step")
    optimizer = [o - f - b - z for o, f, b, z in zip(opt_total, forward, backward, zero_grad, strict=False)]
    parts = {
        "data wait": sum(data),
        "forward (training_step)": sum(forward),
        "backward": sum(backward),
        "optimizer (clip + step)": sum(optimizer),
        "zero_grad": sum(zero_grad),
    }
    parts["other (Lightning, logging)"] = wall - sum(parts.values())

    dm_cfg = cfg["data"]
    vt = cfg["model"]["view_transform"]
    print(
        f"config={args.config} overrides={args.overrides} preset={dm_cfg.get('preset')} batch_size={dm_cfg.get('batch_size')} "
        f"num_workers={dm_cfg.get('num_workers')} view_transform={vt.get('type')} splat={vt.get('splat', 'fast')} "
        f"precision={trainer_args.get('precision', '32-true')} threads={torch.get_num_threads()}"
    )
    print(f"steps measured: {steps} (after {args.warmup} warm-up) in {wall:.2f} s")
    print(f"steps/s: {steps / wall:.3f}   ({wall / steps * 1e3:.0f} ms/step)")
    peak_process = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(
        f"peak RSS: process {peak_process:.0f} MB; during training {rss_peak_fit / 1024:.0f} MB "
        f"({(rss_peak_fit - rss_before) / 1024:+.0f} MB above the {rss_before / 1024:.0f} MB before fit)"
    )
    print("share of step time:")
    for name, seconds in parts.items():
        print(f"  {name:<28}{100 * seconds / wall:6.1f} %   {seconds / steps * 1e3:8.1f} ms/step")
    print(f"data-wait share: {100 * parts['data wait'] / wall:.1f} %")


if __name__ == "__main__":
    main()
