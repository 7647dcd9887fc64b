"""Running a config end to end, as the CLI does."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from occplug.run import runner

__all__ = ["TINY_FIT", "run_config"]

#: Overrides of a short fit on the CPU: one epoch of 2 steps on the tiny world, one validation batch, a checkpoint
#: after every step, deterministic, no progress bar and no data workers (``occplug fit -c <config> *TINY_FIT``;
#: the reliability tests and ``scripts/reliability_corpus.py`` damage and resume such runs).
TINY_FIT: tuple[str, ...] = (
    "data.preset=tiny",
    "data.num_workers=0",
    "trainer.accelerator=cpu",
    "trainer.deterministic=true",
    "trainer.enable_progress_bar=false",
    "trainer.max_epochs=1",
    "trainer.limit_train_batches=2",
    "trainer.limit_val_batches=1",
    "trainer.checkpoint_every_n_steps=1",
)


def run_config(*refs: str, run_dir: Path | str, overrides: Sequence[str] = (), debug: bool = True) -> dict[str, float]:
    """Compose and validate ``refs`` (+ ``occplug/trainer/debug`` unless ``debug=False``), then fit.

    Returns the final validation metrics; the run directory is left for inspection.
    """
    all_refs = [*refs, "occplug/trainer/debug"] if debug else list(refs)
    cfg = runner.load_config(all_refs, overrides)
    if cfg.get("phases") is not None:
        from occplug.run.phases import fit_phases

        return fit_phases(cfg, Path(run_dir))
    return runner.fit(cfg, Path(run_dir))
