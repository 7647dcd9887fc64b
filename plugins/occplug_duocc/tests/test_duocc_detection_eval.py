"""The streamed detector mAP that ablate_duocc.py and duocc_detector_overfit.py report, on the tiny world."""

from types import SimpleNamespace

import pytest
import torch

from occplug import runner
from occplug_duocc.detection_eval import stream_detection_map
from occplug_duocc.queryagg import detection_targets
from occplug_duocc.scene import DETECTION_CLASSES_KEY, DETECTION_KEY

SMALL = ["grid.range=[-8.0,-8.0,-1.0,8.0,8.0,5.4]", "model.encoder.out_channels=16", "model.encoder.width=16"]


@pytest.fixture(scope="module")
def model_and_batches():
    torch.manual_seed(0)
    cfg = runner.load_config(["duocc/full", "occplug/trainer/debug"], ["data.preset=tiny", *SMALL])
    dm, model = runner.build_run(cfg)
    data = dm.dataset("val")
    return model, [dm.collate([data[i]]) for i in range(len(data))]


def _ground_truth_as_detections(model, monkeypatch):
    """The model's forward, its detections replaced by the frame's ground-truth boxes (score ~1, true class)."""
    forward = model.forward

    def cheating_forward(batch):
        out = forward(batch)
        classes = out.extras[DETECTION_CLASSES_KEY]
        labels, boxes = detection_targets(batch, classes, "test")
        logits = torch.full((len(boxes), max(len(b) for b in boxes) + 1, len(classes)), -20.0)
        padded = torch.zeros(logits.shape[:2] + (9,))
        padded[..., :2] = 1e3  # the spare query: far away, never a match
        for i, (lab, box) in enumerate(zip(labels, boxes, strict=True)):
            logits[i, torch.arange(len(lab)), lab] = 20.0
            padded[i, : len(box)] = box
        out.extras[DETECTION_KEY] = SimpleNamespace(cls_logits=[logits], boxes=[padded])
        return out

    monkeypatch.setattr(model, "forward", cheating_forward)


def test_ground_truth_detections_score_a_perfect_map(model_and_batches, monkeypatch):
    model, batches = model_and_batches
    _ground_truth_as_detections(model, monkeypatch)
    # only the true pairs: the devkit's interpolation scores a tail of low-score false positives below 1 at recall 1
    result = stream_detection_map(model, batches, score_threshold=0.5)
    assert result["AP"] and result["mAP"] == pytest.approx(1.0)  # the ground truth holds boxes of some class
    assert 0.9 < stream_detection_map(model, batches)["mAP"] < 1.0
    assert result["classes"] == [int(c) for c in model(batches[0]).extras[DETECTION_CLASSES_KEY]]


def test_the_stream_restarts_so_a_second_pass_scores_the_same(model_and_batches):
    model, batches = model_and_batches
    first = stream_detection_map(model, batches)
    assert 0.0 <= first["mAP"] <= 1.0 and not model.training
    second = stream_detection_map(model, batches)
    assert second["mAP"] == first["mAP"] and second["AP"] == first["AP"]
    assert stream_detection_map(model, [])["classes"] == []
