"""Running a config end to end, as the CLI does."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from occplug.run import runner

__all__ = ["run_config"]


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
