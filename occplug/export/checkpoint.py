"""``occplug export`` from a checkpoint: :func:`export_checkpoint` (rebuild the model, export it, check parity, write
the report) and :func:`check_out` (whether ``--out`` can take the artefact)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from occplug.data.frame import Batch

from .graph import FORMATS, ExportError
from .parity_check import parity, passes, report_path
from .tracing import export_model, load_exported


def export_checkpoint(ckpt: Path, fmt: str, out: Path, samples: int = 4) -> dict[str, Any]:
    """``occplug export``: rebuild the model from ``ckpt`` alone, export it to ``out``, check parity.

    The first ``samples`` frames of the checkpoint's validation split (then of its training split,
    where the validation split is shorter), batch size 1, are the parity frames; the first fixes the
    exported shapes (batch size 1, camera count, image size). A streaming model's frames run in that
    order, as a sequence (:func:`stream_parity`). Writes the report (:func:`parity`, plus
    ``checkpoint``, ``artefact`` and ``passed``) to :func:`report_path` and returns it.

    Raises:
        ExportError / RunError: one line (a bad path, a component that cannot be exported, ...).
    """
    from occplug.run import runner

    ckpt, out = Path(ckpt), Path(out)
    if fmt not in FORMATS:
        raise ExportError(f"--format: {fmt!r} is not one of {', '.join(FORMATS)}")
    if samples < 1:
        raise ExportError(f"--samples: must be >= 1, got {samples}")
    check_out(out)
    cfg = runner.resolve_run_config([], [], ckpt)
    dm, model = runner.restore_run(cfg, runner.load_checkpoint(ckpt), ckpt)
    model.eval()
    batches: list[Batch] = []
    with runner.data_errors():
        for split in ("val", "train"):  # a small validation split is topped up with training frames
            dataset = dm.dataset(split)
            take = min(int(samples) - len(batches), len(dataset))  # type: ignore[arg-type]
            batches += [dm.collate([dataset[i]]) for i in range(max(take, 0))]
    if not batches:
        raise ExportError("data: the validation and training splits are empty; nothing to check the export on")
    export_model(model, batches[0], fmt, out)
    report = parity(model, load_exported(out, fmt), batches, fmt)
    report = {"checkpoint": str(ckpt), "artefact": str(out), **report, "passed": passes(report)}
    runner.write_json(report_path(out), report)
    return report


def check_out(out: Path) -> None:
    """Raise one line when ``--out`` cannot take the artefact (a folder, a missing or non-folder parent)."""
    if out.is_dir():
        raise ExportError(f"--out {out}: is a folder; give the artefact's file name (e.g. {out / 'model.onnx'})")
    parent = out.parent
    if not parent.exists():
        raise ExportError(f"--out {out}: folder {parent} does not exist")
    if not parent.is_dir():
        raise ExportError(f"--out {out}: {parent} is not a folder")
    if not os.access(parent, os.W_OK):
        raise ExportError(f"--out {out}: folder {parent} is not writable")
