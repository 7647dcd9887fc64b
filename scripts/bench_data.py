"""Data-loading benchmark: frames/s of each data module, and the share of a training step spent waiting for data.

    python scripts/bench_data.py                       # default world, 8 training scenes, workers 0 and 2
    python scripts/bench_data.py --preset tiny --batches 10 --steps 10 --workers 0

1. **Throughput.** The synthetic world (frames cached on disk), the same world written as a
   nuScenes-shaped tree read by ``occ3d_nuscenes`` (via ``prepare nuscenes``), and as a
   SemanticKITTI-shaped tree read by ``semantickitti``: each module's training loader is iterated
   for ``--batches`` batches (after one warm-up batch) per ``--workers`` setting; frames/s counts
   key frames delivered as collated batches.
2. **Waiting for data.** ``configs/baseline.yaml`` trains for ``--steps`` steps on the synthetic world
   (the default config but for ``train_scenes``, a selection knob that leaves every frame unchanged);
   a callback measures, per step, the time from the end of one step to the start of the next (the
   loader's ``next()`` plus the batch transfer) against the whole step. The first two steps
   (worker start-up, warm caches) are left out. The goal is < 10 %.

Trees are written under ``--tmp`` (default: a temporary folder, removed at the end). The frames
come from the synthetic world's cache (``$OCCPLUG_CACHE`` or ``~/.cache/occplug``); missing ones are
generated first (slow on a CPU for the default world: keep ``--train-scenes`` small).
"""

from __future__ import annotations

import argparse
import logging
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path

import lightning as L

ROOT = Path(__file__).resolve().parents[1]


def _throughput(dm, batches: int) -> tuple[float, int]:  # noqa: ANN001
    loader = dm.train_dataloader()
    it = iter(loader)
    next(it)  # warm-up: worker start-up, first decode
    frames = 0
    start = time.perf_counter()
    for _ in range(batches):
        try:
            batch = next(it)
        except StopIteration:
            it = iter(loader)
            batch = next(it)
        frames += len(batch)
    return frames / (time.perf_counter() - start), frames


class _WaitTimer(L.Callback):
    """Per step: time between the end of the previous step and the start of this one (= waiting for data)."""

    def __init__(self) -> None:
        self.waits: list[float] = []
        self.steps: list[float] = []
        self._end: float | None = None
        self._start = 0.0

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:  # noqa: ANN001
        now = time.perf_counter()
        if self._end is not None:
            self.waits.append(now - self._end)
        self._start = now

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:  # noqa: ANN001
        now = time.perf_counter()
        self.steps.append(now - self._start)
        self._end = now


def _wait_fraction(preset: str, train_scenes: int, workers: int, steps: int) -> tuple[float, float, float]:
    from occplug.run import runner

    cfg = runner.load_config(
        [str(ROOT / "configs" / "baseline.yaml")],
        [
            f"data.preset={preset}",
            f"data.train_scenes={train_scenes}",
            "data.val_scenes=1",
            "data.test_scenes=0",
            f"data.num_workers={workers}",
            f"trainer.max_steps={steps}",
            "trainer.limit_val_batches=0",
            "trainer.enable_progress_bar=false",
            "trainer.accelerator=cpu",
        ],
    )
    L.seed_everything(0, verbose=False)
    dm = runner.build_datamodule(cfg)
    model = runner.build_model(cfg, dm)
    timer = _WaitTimer()
    trainer = L.Trainer(
        callbacks=[timer], logger=False, enable_checkpointing=False, enable_model_summary=False, **cfg["trainer"]
    )
    trainer.fit(model, datamodule=dm)
    waits = timer.waits[1:]  # waits[0] precedes step 2; skip steps 1-2
    steps_t = timer.steps[2:]
    wait, compute = sum(waits), sum(steps_t)
    return wait / (wait + compute), (wait + compute) / max(1, len(steps_t)), wait / max(1, len(waits))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="default")
    p.add_argument("--train-scenes", type=int, default=8, help="training scenes used (a selection knob; default 8)")
    p.add_argument("--batch-size", type=int, default=2)
    p.add_argument("--batches", type=int, default=20, help="batches timed per data module and worker setting")
    p.add_argument("--workers", type=int, nargs="+", default=[0, 2])
    p.add_argument("--steps", type=int, default=30, help="training steps for the waiting share")
    p.add_argument("--tmp", default=None, help="folder for the written trees (default: a temporary one)")
    args = p.parse_args(argv)

    from occplug.data import Occ3DNuScenesDataModule, SemanticKITTIDataModule, build_index
    from occplug.data.synthetic import SyntheticDataModule, lidar_grid, write_occ3d_nuscenes, write_semantickitti

    logging.getLogger("lightning.pytorch").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore")
    tmp = Path(args.tmp) if args.tmp else Path(tempfile.mkdtemp(prefix="occplug-bench-"))
    try:
        base = SyntheticDataModule(preset=args.preset, train_scenes=args.train_scenes, val_scenes=0, test_scenes=0)
        t0 = time.perf_counter()
        base.dataset("train").pregenerate(progress=True)  # type: ignore[attr-defined]
        world = base.world_config
        print(
            f"synthetic world '{args.preset}' ({args.train_scenes} training scenes x {world.frames_per_scene} frames, "
            f"{world.num_cameras} cameras {world.image_size[0]}x{world.image_size[1]}, grid {world.grid.shape}); "
            f"cache ready in {time.perf_counter() - t0:.1f} s"
        )
        ns, kitti = tmp / "nuscenes", tmp / "semantickitti"
        if not (ns / "index").exists():
            write_occ3d_nuscenes(world, ns, splits=("train",), progress=False)
            build_index(ns, "v1.0-trainval", ns / "index", occ_root=ns, splits=ns / "splits.json", progress=False)
        if not kitti.exists():
            write_semantickitti(world, kitti, splits=("train",), progress=False)
        # only training sequences are written: no val sequence (a split none of whose sequences is present fails)
        splits = {"train": [f"{i:02d}" for i in range(args.train_scenes)], "val": []}
        modules = {
            "synthetic": lambda w: SyntheticDataModule(
                preset=args.preset, train_scenes=args.train_scenes, batch_size=args.batch_size, num_workers=w
            ),
            "occ3d_nuscenes": lambda w: Occ3DNuScenesDataModule(
                root=str(ns),
                index=str(ns / "index"),
                grid=world.grid.to_dict(),
                batch_size=args.batch_size,
                num_workers=w,
            ),
            "semantickitti": lambda w: SemanticKITTIDataModule(
                root=str(kitti),
                grid=lidar_grid(world).to_dict(),
                batch_size=args.batch_size,
                num_workers=w,
                splits=splits,
            ),
        }
        print(
            f"\nthroughput (training loader, batch size {args.batch_size}, {args.batches} batches after a warm-up batch)"
        )
        print(f"{'data module':<16} {'workers':>7} {'frames/s':>9}")
        for name, make in modules.items():
            for w in args.workers:
                fps, _ = _throughput(make(w), args.batches)
                print(f"{name:<16} {w:>7} {fps:>9.1f}")
        print(
            f"\nwaiting for data during training (configs/baseline.yaml on '{args.preset}', {args.steps} steps, first 2 left out)"
        )
        print(f"{'workers':>7} {'step s':>8} {'wait s':>8} {'waiting':>8}")
        for w in args.workers:
            frac, step, wait = _wait_fraction(args.preset, args.train_scenes, w, args.steps)
            print(f"{w:>7} {step:>8.3f} {wait:>8.4f} {100 * frac:>7.1f}%")
    finally:
        if not args.tmp:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
