"""The detector's nuScenes-style mAP: the metric (:func:`detection_map`) and its run over a stream of batches,
read in order as evaluation reads them (:func:`stream_detection_map`).

:func:`detection_map` follows the nuScenes devkit (greedy matching by score within each class, 101-point
precision interpolation without an envelope, ``min_recall = min_precision = 0.1``); classes are those present
in the ground truth.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import torch
from torch import Tensor

from occplug.data import Batch
from occplug.streams import find_streams, set_stream_stage

from ..blocks.detector import select_detections
from ..blocks.queryagg import detection_targets
from ..scene import DETECTION_CLASSES_KEY, DETECTION_KEY

__all__ = ["detection_map", "stream_detection_map"]


def _average_precision(tp: np.ndarray, npos: int, min_recall: float, min_precision: float) -> float:
    """nuScenes ``accumulate`` + ``calc_ap`` for one class and threshold (``tp`` in descending-score order)."""
    if tp.size == 0 or tp.sum() == 0:
        return 0.0
    ctp, cfp = np.cumsum(tp), np.cumsum(1 - tp)
    prec = ctp / (ctp + cfp)
    rec = ctp / float(npos)
    prec = np.interp(np.linspace(0, 1, 101), rec, prec, right=0)
    prec = prec[round(100 * min_recall) + 1 :] - min_precision
    prec[prec < 0] = 0
    return float(np.mean(prec)) / (1.0 - min_precision)


def detection_map(
    pred_boxes: Sequence[Tensor],
    pred_scores: Sequence[Tensor],
    pred_labels: Sequence[Tensor],
    gt_boxes: Sequence[Tensor],
    gt_labels: Sequence[Tensor],
    thresholds: Sequence[float] = (0.5, 1.0, 2.0, 4.0),
    min_recall: float = 0.1,
    min_precision: float = 0.1,
) -> dict[str, object]:
    """nuScenes-style mean average precision by BEV centre distance.

    Per class present in the ground truth and per threshold: predictions of that class (all samples) are taken
    by descending score; each is a true positive when the nearest not-yet-matched ground truth of its class in
    its sample lies within the threshold (BEV centre distance, metres, strict ``<``), which it then consumes.
    AP is the devkit's: precision interpolated at 101 recalls, recalls up to ``min_recall`` dropped,
    ``max(p - min_precision, 0)`` averaged and divided by ``1 - min_precision`` (0 and 0 give plain 101-point AP).

    Args:
        pred_boxes: ``B`` tensors ``(P_b, >=2)`` (only the centre ``x, y`` is used), ego frame.
        pred_scores: ``B`` tensors ``(P_b,)``.
        pred_labels: ``B`` tensors ``(P_b,)`` int64.
        gt_boxes: ``B`` tensors ``(G_b, >=2)``, ego frame.
        gt_labels: ``B`` tensors ``(G_b,)`` int64.
        thresholds: centre-distance thresholds, metres (nuScenes 0.5, 1, 2, 4).
        min_recall, min_precision: the devkit's 0.1 and 0.1.

    Returns:
        ``{"mAP": float (0 without ground truth), "AP": {class: AP averaged over thresholds},
        "AP@": {threshold: AP averaged over classes}}``.
    """
    n = len(gt_boxes)
    if not len(pred_boxes) == len(pred_scores) == len(pred_labels) == len(gt_labels) == n:
        raise ValueError("detection_map: every argument needs one entry per sample")

    def np_(t: Tensor) -> np.ndarray:
        return t.detach().cpu().numpy()

    gt_xy = [np_(g[:, :2]).astype(np.float64) for g in gt_boxes]
    gt_cls = [np_(g).astype(np.int64) for g in gt_labels]
    classes = sorted(set(np.concatenate(gt_cls).tolist())) if n else []
    table = np.zeros((len(classes), len(thresholds)))
    for ci, c in enumerate(classes):
        npos = int(sum((g == c).sum() for g in gt_cls))
        preds = []  # (score, sample, xy)
        for s in range(n):
            lab = np_(pred_labels[s]).astype(np.int64)
            sc, xy = np_(pred_scores[s]).astype(np.float64), np_(pred_boxes[s][:, :2]).astype(np.float64)
            preds += [(sc[i], s, xy[i]) for i in np.nonzero(lab == c)[0]]
        order = np.argsort([-p[0] for p in preds], kind="stable")
        for ti, thr in enumerate(thresholds):
            taken = [np.zeros(int((g == c).sum()), dtype=bool) for g in gt_cls]
            tp = np.zeros(len(preds))
            for rank, pi in enumerate(order):
                _, s, xy = preds[pi]
                cand = gt_xy[s][gt_cls[s] == c]
                if cand.shape[0] == 0:
                    continue
                dist = np.linalg.norm(cand - xy, axis=1)
                dist[taken[s]] = np.inf
                j = int(np.argmin(dist))
                if dist[j] < thr:
                    taken[s][j] = True
                    tp[rank] = 1.0
            table[ci, ti] = _average_precision(tp, npos, min_recall, min_precision)
    return {
        "mAP": float(table.mean()) if table.size else 0.0,
        "AP": {int(c): float(table[ci].mean()) for ci, c in enumerate(classes)},
        "AP@": {float(t): float(table[:, ti].mean()) if classes else 0.0 for ti, t in enumerate(thresholds)},
    }


def stream_detection_map(
    model: torch.nn.Module, batches: Iterable[Batch], stage: str = "val", top_k: int = 100, score_threshold: float = 0.0
) -> dict:
    """nuScenes-style mAP of a DuOcc model's detector over ``batches`` in order (:func:`detection_map`).

    The stream state of ``stage`` is cleared first and carried from batch to batch, as in evaluation. The model is
    left in eval mode.

    Args:
        model: a composed model whose outputs carry the detector's (``outputs.extras[DETECTION_KEY]``).
        batches: batches of one stream (a validation loader, or the first training batches in order).
        stage: the stream-state stage to read and write (``"val"``, ``"train"``, ...).
        top_k, score_threshold: which (query, class) pairs a frame reports (:func:`~.detector.select_detections`;
            the scripts' 100 and 0: every pair of a small query set counts, low scores last).

    Returns:
        :func:`detection_map`'s result (``"mAP"`` in [0, 1], ``"AP"`` per detection class index) and
        ``"classes"``: the label id of each detection class index (empty when ``batches`` is).
    """
    model.eval()
    set_stream_stage(model, stage)
    for _, state in find_streams(model):
        state.clear(stage)
    preds: tuple[list, list, list] = ([], [], [])
    gts: tuple[list, list] = ([], [])
    classes: list[int] = []
    with torch.no_grad():
        for batch in batches:
            out = model(batch)
            classes = [int(c) for c in out.extras[DETECTION_CLASSES_KEY]]
            for boxes, scores, labels in select_detections(out.extras[DETECTION_KEY], top_k, score_threshold):
                preds[0].append(boxes)
                preds[1].append(scores)
                preds[2].append(labels)
            labels, boxes = detection_targets(batch, classes, "stream_detection_map")
            gts[0].extend(boxes)
            gts[1].extend(labels)
    result = detection_map(*preds, *gts)
    result["classes"] = classes
    return result
