"""The ground-truth-box oracle's real control (duocc/constant_gt_boxes) and its noisy version (duocc/noisy_gt_boxes)."""

import dataclasses

import pytest
import torch

from occplug.run import runner
from occplug.streams import find_streams, set_stream_stage
from occplug_duocc.blocks.queryagg import detection_targets

#: the tiny world on a 16 m grid with narrow image features, as the other DuOcc tests
SMALL = ["grid.range=[-8.0,-8.0,-1.0,8.0,8.0,5.4]", "model.encoder.out_channels=16", "model.encoder.width=16"]


def _model_and_dm(config, *overrides):
    cfg = runner.load_config([f"duocc/{config}", "occplug/trainer/debug"], [*SMALL, "data.preset=tiny", *overrides])
    dm, model = runner.build_run(cfg)
    return model, dm


def _batch(dm, indices):
    data = dm.dataset("train")
    return dm.collate([data[i] for i in indices])


def test_the_constant_control_writes_one_embedding_into_every_ground_truth_box():
    torch.manual_seed(0)
    model, dm = _model_and_dm("constant_gt_boxes")
    qa = model.scene.query_agg
    assert qa.v2q is None and qa.class_embed is None and qa.constant_embed.shape == (32,)
    batch = _batch(dm, [0, 3])
    calls = []
    qa.dqa.register_forward_hook(lambda m, args, out: calls.append(args))
    model.eval()
    set_stream_stage(model, "val")

    def fresh_forward():
        for _, state in find_streams(model):
            state.clear("val")
        return model(batch).scene.features

    with torch.no_grad():
        first = fresh_forward()
        qa.detector.register_forward_hook(lambda m, i, out: dataclasses.replace(out, features=out.features + 1.0))
        second = fresh_forward()
    assert torch.equal(first, second)  # the detector's features never reach the voxels
    _, queries, _, sel = calls[-1]
    labels, _ = detection_targets(batch, qa.classes, "test")
    for b in range(2):
        assert int(sel[b].sum()) == labels[b].shape[0] > 0  # one query per ground-truth box
        assert torch.equal(queries[b, sel[b]], qa.constant_embed.expand(labels[b].shape[0], -1))  # all one vector
    # the constant learns
    model.train()
    set_stream_stage(model, "train")
    losses = model.losses(batch, model(batch))
    torch.stack(list(losses.values())).sum().backward()
    assert bool(qa.constant_embed.grad.abs().gt(0).any())
    with pytest.raises(runner.RunError, match="write: constant is what DQA writes: it needs dqa: true"):
        _model_and_dm(
            "full",
            "model.scene.query_agg.write=constant",
            "model.scene.query_agg.dqa=false",
            "model.scene.query_agg.v2q=false",
        )


def test_the_noisy_oracle_is_the_oracle_with_its_centres_moved_by_the_detectors_error():
    torch.manual_seed(0)
    noisy, dm = _model_and_dm("noisy_gt_boxes")
    qa = noisy.scene.query_agg
    assert qa.gt_boxes and qa.gt_box_noise == 2.4 and qa.gt_box_drop == 0.0 and qa.write == "instance"
    batch = _batch(dm, [0, 3])
    calls = []
    qa.dqa.register_forward_hook(lambda m, args, out: calls.append(args))
    noisy.eval()
    with torch.no_grad():
        noisy(batch)
    _, _, boxes, sel = calls[-1]
    _, gts = detection_targets(batch, qa.classes, "test")
    moved = []
    for b in range(2):
        got, expected = boxes[b, sel[b]], gts[b].to(boxes)
        assert got.shape == expected.shape
        # each written box is a true box whose centre moved in x and y only (matched by its size, height, yaw)
        order = lambda t: t[t[:, 2:].sum(-1).argsort()]  # noqa: E731
        got, expected = order(got), order(expected)
        assert torch.equal(got[:, 2:], expected[:, 2:])
        moved.append((got[:, :2] - expected[:, :2]).norm(dim=-1))
    assert 0.5 < float(torch.cat(moved).mean()) < 8.0  # metres: the order of 2.4 * sqrt(pi / 2) = 3.0
