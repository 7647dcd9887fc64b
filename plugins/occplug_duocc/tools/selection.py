"""What QueryAgg's selection hands DQA on the validation stream: how many queries, how many of them are real, and
which voxels DQA writes.

Reads a run's checkpoint and streams the validation split in order, as evaluation does (no training)::

    python -m occplug_duocc.tools.selection runs/duocc_ablate/full-seed0                 # the run's last.ckpt
    python -m occplug_duocc.tools.selection RUN --thresholds 0.1 0.2 0.3 0.5 --json out.json

Per frame it counts, for the learned detector's last layer:

* for each score threshold ``s``: the queries a score-only selection takes (``score > s``, the largest class
  sigmoid, as :func:`~occplug_duocc.blocks.dqa.select_queries` without ground truth), and their **precision**: the share
  whose box centre lies within ``--radius`` (1 m) in ``x, y`` of a ground-truth box centre of a detection class;
  and the ground-truth boxes' **recall**: the share with a taken query within that radius;
* for every ground-truth box, the distance (x, y) to the nearest query centre of any score (its mean: how close
  the detector's boxes come to the objects at all);
* the queries the model itself selected (``duocc_stream/dqa_selected``: at evaluation the score rule at the
  run's ``score_threshold``), their precision, and what DQA wrote: the voxels its boxes cover under the run's
  coverage rule (:meth:`~occplug_duocc.blocks.dqa.DynamicQueryAggregation.edges`), and the share of those that the same
  rule puts inside a ground-truth box.

Every count is a mean per frame. A run trained with ``gt_boxes: true`` at evaluation is not what this reads: it
reports the detector's own boxes.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path

import torch
from torch import Tensor

from occplug import UserError
from occplug.data import Batch
from occplug.streams import find_streams, set_stream_stage

from ..blocks.dqa import DynamicQueryAggregation
from ..blocks.queryagg import detection_targets
from ..scene import DETECTION_CLASSES_KEY, DETECTION_KEY, DQA_SELECTED_KEY

__all__ = ["SelectionTally", "near_a_box", "stream_selection_report", "main"]

#: the score thresholds reported by default (DuOcc's evaluation takes 0.3)
THRESHOLDS = (0.1, 0.2, 0.3, 0.4, 0.5)


def near_a_box(centres: Tensor, boxes: Tensor, radius: float) -> tuple[Tensor, Tensor]:
    """Which of ``(Q, 2)`` query centres lie within ``radius`` metres (x, y) of one of ``(G, >=2)`` box centres, and
    which boxes have such a query: ``(Q,)`` and ``(G,)`` bool."""
    if len(centres) == 0 or len(boxes) == 0:
        return torch.zeros(len(centres), dtype=torch.bool), torch.zeros(len(boxes), dtype=torch.bool)
    close = torch.cdist(centres.double(), boxes[:, :2].double()) <= radius  # (Q, G)
    return close.any(1), close.any(0)


class SelectionTally:
    """Sums over frames of the counts :func:`stream_selection_report` reports (see the module docstring)."""

    def __init__(self, thresholds: Sequence[float]) -> None:
        self.thresholds = [float(t) for t in thresholds]
        self.frames = 0
        self.boxes = 0
        self.taken = [0] * len(self.thresholds)
        self.true = [0] * len(self.thresholds)
        self.found = [0] * len(self.thresholds)
        self.selected = self.selected_true = self.written = self.written_in_box = 0
        self.nearest = 0.0  # summed over true boxes: metres (x, y) to the nearest query centre, any score

    def add(
        self,
        scores: Tensor,
        centres: Tensor,
        gt_boxes: Tensor,
        selected: Tensor | None,
        written: Tensor | None,
        gt_written: Tensor | None,
        radius: float,
    ) -> None:
        """One frame: ``scores`` ``(Q,)``, ``centres`` ``(Q, 2)`` of the queries' boxes, ``gt_boxes`` ``(G, >=7)``
        (ego frame), ``selected`` ``(Q,)`` bool (the model's own selection), ``written`` / ``gt_written`` the flat
        voxel indices DQA's coverage gives the selected boxes / the ground-truth boxes."""
        self.frames += 1
        self.boxes += len(gt_boxes)
        real, _ = near_a_box(centres, gt_boxes, radius)
        if len(gt_boxes) and len(centres):
            self.nearest += float(torch.cdist(gt_boxes[:, :2].double(), centres.double()).amin(1).sum())
        for i, t in enumerate(self.thresholds):
            take = scores > t
            self.taken[i] += int(take.sum())
            self.true[i] += int((take & real).sum())
            self.found[i] += int(near_a_box(centres[take], gt_boxes, radius)[1].sum())
        if selected is not None:
            self.selected += int(selected.sum())
            self.selected_true += int((selected & real).sum())
        if written is not None and gt_written is not None:
            written = written.unique()
            self.written += len(written)
            self.written_in_box += int(torch.isin(written, gt_written).sum())

    def report(self) -> dict:
        """Per-frame means, precision and recall in percent (``None`` where nothing was taken or there was no box)."""
        n = max(self.frames, 1)

        def pct(a: int, b: int) -> float | None:
            return round(100.0 * a / b, 2) if b else None

        return {
            "frames": self.frames,
            "true_boxes_per_frame": round(self.boxes / n, 2),
            "nearest_query_to_a_true_box_m": round(self.nearest / self.boxes, 3) if self.boxes else None,
            "by_score_threshold": {
                f"{t:g}": {
                    "queries_per_frame": round(self.taken[i] / n, 2),
                    "precision_pct": pct(self.true[i], self.taken[i]),
                    "recall_pct": pct(self.found[i], self.boxes),
                }
                for i, t in enumerate(self.thresholds)
            },
            "model_selection": {
                "queries_per_frame": round(self.selected / n, 2),
                "precision_pct": pct(self.selected_true, self.selected),
                "voxels_written_per_frame": round(self.written / n, 2),
                "written_inside_a_true_box_pct": pct(self.written_in_box, self.written),
            },
        }


def stream_selection_report(
    model: torch.nn.Module,
    batches: Iterable[Batch],
    stage: str = "val",
    thresholds: Sequence[float] = THRESHOLDS,
    radius: float = 1.0,
) -> dict:
    """:class:`SelectionTally`'s report over ``batches`` read in order as one stream (the stage's stream state is
    cleared first, as :func:`~occplug_duocc.tools.detection_eval.stream_detection_map` does). The model is left in eval
    mode."""
    dqa = next((m for m in model.modules() if isinstance(m, DynamicQueryAggregation)), None)
    model.eval()
    set_stream_stage(model, stage)
    for _, state in find_streams(model):
        state.clear(stage)
    tally = SelectionTally(thresholds)
    with torch.no_grad():
        for batch in batches:
            out = model(batch)
            if DETECTION_KEY not in out.extras:
                raise UserError("the model has no detector (model.scene.query_agg): nothing to report")
            det = out.extras[DETECTION_KEY]
            scores = det.cls_logits[-1].sigmoid().amax(-1)  # (B, Q)
            boxes = det.boxes[-1]  # (B, Q, 9) ego frame
            chosen = out.extras.get(DQA_SELECTED_KEY)
            _, gts = detection_targets(batch, list(out.extras[DETECTION_CLASSES_KEY]), "selection report")
            for b, gt in enumerate(gts):
                written = gt_written = None
                sel = None if chosen is None else chosen[b].bool()
                if dqa is not None and sel is not None:
                    written = dqa.edges(boxes[b][sel])[0]
                    gt_written = dqa.edges(gt.to(boxes))[0]
                tally.add(scores[b], boxes[b, :, :2], gt, sel, written, gt_written, radius)
    return tally.report()


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m occplug_duocc.tools.selection",
        description=__doc__,
        formatter_class=argparse.RawTextHelpFormatter,
    )
    parser.add_argument("run", type=Path, help="a run directory (its checkpoints/last.ckpt) or a checkpoint file")
    parser.add_argument("--thresholds", type=float, nargs="+", default=list(THRESHOLDS), help="score thresholds")
    parser.add_argument("--radius", type=float, default=1.0, help="metres (x, y) to a true box centre (default 1)")
    parser.add_argument("--json", type=Path, default=None, help="also write the report here")
    args = parser.parse_args(argv)

    from occplug.run.runner import RunError, config_from_checkpoint, data_errors, load_checkpoint, restore_run

    path = args.run / "checkpoints" / "last.ckpt" if args.run.is_dir() else args.run
    try:
        if args.radius <= 0:
            raise UserError(f"--radius must be positive, got {args.radius:g}")
        ckpt = load_checkpoint(path)
        cfg = config_from_checkpoint(ckpt, path)
        dm, model = restore_run(cfg, ckpt, path)
        with data_errors():
            dm.prepare_data()
            dm.setup("validate")
            report = stream_selection_report(model, dm.val_dataloader(), "val", args.thresholds, args.radius)
    except (RunError, UserError, LookupError) as exc:
        print(f"error: {path}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}", file=sys.stderr)
        return 2
    report["checkpoint"] = str(path)
    print(json.dumps(report, indent=2))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
