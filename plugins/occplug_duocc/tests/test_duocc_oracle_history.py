"""duocc_stream history_source: ground_truth (duocc/stream_agg_oracle_history): a perfect history, StreamAgg's oracle."""

import pytest
import torch

from occplug.geometry import class_fractions
from occplug.run import runner
from occplug.streams import set_stream_stage

#: the tiny world on a 16 m grid (V_curr 10 x 10 x 4) with narrow image features, as the other DuOcc tests
SMALL = ["grid.range=[-8.0,-8.0,-1.0,8.0,8.0,5.4]", "model.encoder.out_channels=16", "model.encoder.width=16"]


def _model_and_dm(config, *overrides):
    cfg = runner.load_config([f"duocc/{config}", "occplug/trainer/debug"], [*SMALL, "data.preset=tiny", *overrides])
    dm, model = runner.build_run(cfg)
    return model, dm


def _batch(dm, indices, split="val"):
    data = dm.dataset(split)
    return dm.collate([data[i] for i in indices])


def _pair():
    """``duocc/stream_agg_concat`` and its oracle with equal weights (the oracle's own table aside)."""
    torch.manual_seed(0)
    learned, dm = _model_and_dm("stream_agg_concat")
    torch.manual_seed(0)
    oracle, _ = _model_and_dm("stream_agg_oracle_history")
    missing, unexpected = oracle.load_state_dict(learned.state_dict(), strict=False)
    assert missing == ["scene.history_embedding.weight"] and not unexpected
    return learned, oracle, dm


def test_the_oracle_changes_the_output_only_through_the_history():
    learned, oracle, dm = _pair()
    assert learned.scene.history_embedding is None and oracle.scene.history_embedding.weight.shape == (18, 32)
    frames = [_batch(dm, [i]) for i in range(2)]  # one val scene, frames 0 and 1
    assert bool(frames[0].is_sequence_start[0]) and not bool(frames[1].is_sequence_start[0])
    outs = {}
    for name, model in (("learned", learned), ("oracle", oracle)):
        model.eval()
        set_stream_stage(model, "val")
        with torch.no_grad():
            outs[name] = [model(f).scene.features for f in frames]
    assert torch.equal(outs["learned"][0], outs["oracle"][0])  # a stream start reads V_curr in both
    assert not torch.allclose(outs["learned"][1], outs["oracle"][1])  # the history differs
    # what the oracle stored for frame 1 is frame 0's class shares on the coarse grid, not V_fin
    stored = oracle.scene.history._stores["val"][0].value
    assert torch.equal(stored, class_fractions(frames[1].voxel_labels, 18, 2)[0])
    # and frame 1 of the oracle equals the learned model fed the embedded shares of frame 0 as its history
    oracle.scene.history.clear("val")
    with torch.no_grad():
        oracle(frames[0])
        learned.scene.history.clear("val")
        learned(frames[0])  # the stream's bookkeeping (scene, frame, pose) of frame 0; its value is replaced below
        shares = oracle.scene.history._stores["val"][0].value
        learned.scene.history._stores["val"][0].value = torch.einsum(
            "kxyz,kc->cxyz", shares, oracle.scene.history_embedding.weight
        )
        torch.testing.assert_close(learned(frames[1]).scene.features, oracle(frames[1]).scene.features)


def test_the_oracles_embedding_learns_through_the_warp():
    _, oracle, dm = _pair()
    oracle.train()
    set_stream_stage(oracle, "train")
    frames = [_batch(dm, [i], "train") for i in range(2)]
    oracle(frames[0])
    losses = oracle.losses(frames[1], oracle(frames[1]))
    torch.stack(list(losses.values())).sum().backward()
    grad = oracle.scene.history_embedding.weight.grad
    present = class_fractions(frames[0].voxel_labels, 18, 2).sum((0, 2, 3, 4)) > 0
    assert bool(grad[present].abs().sum(1).gt(0).all())  # every class in frame 0's labels gets gradient
    assert bool(grad[~present].eq(0).all())  # and no other


def test_the_oracle_needs_a_stream_and_labels():
    with pytest.raises(runner.RunError, match="history_source: ground_truth needs stream: true"):
        _model_and_dm("stream_agg_oracle_history", "model.scene.stream=false")
    _, oracle, dm = _pair()
    oracle.eval()
    batch = _batch(dm, [0])
    batch.voxel_labels = None
    with pytest.raises(ValueError, match=r"history_source: ground_truth reads batch.voxel_labels .* got None$"):
        oracle(batch)
