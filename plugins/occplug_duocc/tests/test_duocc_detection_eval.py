"""The streamed detector mAP that occplug_duocc.tools.ablate and investigations/duocc/detector_overfit.py report, on the
tiny world."""

from types import SimpleNamespace

import pytest
import torch

from occplug_duocc.blocks.queryagg import detection_targets
from occplug_duocc.scene import DETECTION_CLASSES_KEY, DETECTION_KEY
from occplug_duocc.tools.detection_eval import stream_detection_map


def _frames(dm, split="val"):
    data = dm.dataset(split)
    return [data[i] for i in range(len(data))]


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


def test_ground_truth_detections_score_a_perfect_map(model_dm, monkeypatch):
    model, dm = model_dm
    frames = _frames(dm)
    _ground_truth_as_detections(model, monkeypatch)
    # one frame per batch, and the frames side by side in one batch (predictions and ground truth stay paired)
    for batches in ([dm.collate([f]) for f in frames], [dm.collate(frames)]):
        # only the true pairs: the devkit's interpolation scores a tail of low-score false positives below 1
        result = stream_detection_map(model, batches, score_threshold=0.5)
        assert result["AP"] and result["mAP"] == pytest.approx(1.0)  # the ground truth holds boxes of some class
        assert 0.9 < stream_detection_map(model, batches)["mAP"] < 1.0
        assert result["classes"] == [int(c) for c in model(batches[0]).extras[DETECTION_CLASSES_KEY]]


def test_each_pass_starts_from_a_cleared_stream(model_dm, monkeypatch):
    """A pass reads the same detections whatever ran before it: its stream state is cleared first.

    The stream resets by itself when time does not move forward, so the pass before must end on an earlier frame of
    the same scene: frame 1, then a pass over frame 2 (0.5 s later) would read frame 1's history without the clear.
    """
    import occplug_duocc.tools.detection_eval as detection_eval

    model, dm = model_dm
    seen: list[list] = []
    select = detection_eval.select_detections

    def recording(*args, **kwargs):
        out = select(*args, **kwargs)
        seen[-1].append(out)
        return out

    monkeypatch.setattr(detection_eval, "select_detections", recording)
    frames = _frames(dm, "train")
    first, second = dm.collate([frames[1]]), dm.collate([frames[2]])  # frames 1 and 2 of the first training scene
    assert not bool(second.is_sequence_start.any())
    results = []
    for batches in ([second], [first], [second]):
        seen.append([])
        results.append(stream_detection_map(model, batches, stage="train"))
    assert not model.training and 0.0 <= results[0]["mAP"] <= 1.0
    (boxes_a, scores_a, _), (boxes_b, scores_b, _) = seen[0][0][0], seen[2][0][0]
    assert torch.equal(boxes_a, boxes_b) and torch.equal(scores_a, scores_b)
    assert stream_detection_map(model, [])["classes"] == []


def test_the_regression_gate_is_a_config_value(model_dm):
    """duocc_detection's reg_score_threshold reaches the loss: at 1 no match is regressed, with None every one is."""
    from occplug_duocc.supervision import DuOccDetection

    model, dm = model_dm
    data = dm.dataset("train")
    batch = dm.collate([data[0], data[3]])
    model.train()
    out = model(batch)
    gated = DuOccDetection(reg_score_threshold=1.0).train()(batch, out)
    open_gate = DuOccDetection(reg_score_threshold=None).train()(batch, out)
    assert float(gated["det_box"]) == 0.0 < float(open_gate["det_box"])
    assert torch.equal(gated["det_cls"], open_gate["det_cls"])  # the gate touches the box term only
