"""The detector's mAP over a stream of batches, read in order as evaluation reads them."""

from __future__ import annotations

from collections.abc import Iterable

import torch

from occplug.data import Batch
from occplug.streams import find_streams, set_stream_stage

from .detector import detection_map, select_detections
from .queryagg import detection_targets
from .scene import DETECTION_CLASSES_KEY, DETECTION_KEY


def stream_detection_map(
    model: torch.nn.Module, batches: Iterable[Batch], stage: str = "val", top_k: int = 100, score_threshold: float = 0.0
) -> dict:
    """nuScenes-style mAP of a DuOcc model's detector over ``batches`` in order (:func:`.detector.detection_map`).

    The stream state of ``stage`` is cleared first and carried from batch to batch, as in evaluation. The model is
    left in eval mode.

    Args:
        model: a composed model whose outputs carry the detector's (``outputs.extras[DETECTION_KEY]``).
        batches: batches of one stream (a validation loader, or the first training batches in order).
        stage: the stream-state stage to read and write (``"val"``, ``"train"``, ...).
        top_k, score_threshold: which (query, class) pairs a frame reports (:func:`.detector.select_detections`;
            the scripts' 100 and 0: every pair of a small query set counts, low scores last).

    Returns:
        :func:`.detector.detection_map`'s result (``"mAP"`` in [0, 1], ``"AP"`` per detection class index) and
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
