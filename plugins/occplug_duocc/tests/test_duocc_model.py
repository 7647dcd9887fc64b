"""DuOcc as an occplug model (Tab. 4 A and B, the Tab. 5 rows, the stacking baseline) on the tiny world."""

import lightning as L
import pytest
import torch

from occplug import runner
from occplug.streams import set_stream_stage

# 20 x 20 x 8 label voxels (V_curr 10 x 10 x 4): the recipes' 60 x 60 x 8 shrunk for test speed
SMALL = ["grid.range=[-8.0,-8.0,-1.0,8.0,8.0,5.4]", "model.encoder.out_channels=16", "model.encoder.width=16"]
CONFIGS = ["single_frame", "stream_agg", "stream_warp_only", "stream_refine", "stream_refine_forecast", "stacking"]


def _model_and_dm(config="stream_agg", *overrides):
    cfg = runner.load_config([f"duocc/{config}", "occplug/trainer/debug"], [*SMALL, *overrides])
    dm, model = runner.build_run(cfg)
    return model, dm


def _batch(dm, indices, split="train"):
    data = dm.dataset(split)
    return dm.collate([data[i] for i in indices])


def _loss(model, batch):
    losses = model.losses(batch, model(batch))
    return torch.stack(list(losses.values())).sum(), losses


@pytest.mark.parametrize("config", CONFIGS)
def test_config_builds_and_the_loss_falls_on_one_repeated_batch(config):
    torch.manual_seed(0)
    model, dm = _model_and_dm(config)
    batch = _batch(dm, [0, 3])  # two scenes (3 frames each in the tiny world)
    _, terms = _loss(model, batch)
    aux = {"forecast/forecast_ce", "occupied/occupied_bce"}
    expected = {"depth/depth", "occupancy/voxel_ce"}
    expected |= {
        "stream_agg": aux,
        "stream_refine_forecast": {"forecast/forecast_ce"},
    }.get(config, set())
    assert set(terms) == expected
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3)
    history = []
    for _ in range(4):
        loss, _ = _loss(model, batch)
        assert torch.isfinite(loss)
        opt.zero_grad()
        loss.backward()
        opt.step()
        history.append(float(loss.detach()))
    assert history[-1] < history[0]
    model.eval()
    pred = model.predict_occupancy(batch)
    assert pred.shape == (2, 20, 20, 8) and pred.dtype == torch.int64
    assert 0 <= int(pred.min()) and int(pred.max()) < model.num_classes


def test_single_frame_keeps_no_state_and_stream_agg_does():
    single, _ = _model_and_dm("single_frame")
    stream, _ = _model_and_dm("stream_agg")
    assert single.scene.agg is None and not hasattr(single.scene, "history") and not single.scene.stateful
    assert stream.scene.stateful and stream.scene.agg.fusion == "add" and stream.scene.history.max_gap_s == 2.0
    concat, _ = _model_and_dm("stream_agg", "model.scene.fusion=concat")
    assert concat.scene.agg.fusion == "concat"


def _capture(module):
    """Record the inputs and output of ``module.forward`` (the real component's calls)."""
    calls = []
    module.register_forward_hook(lambda m, args, out: calls.append((args, out)))
    return calls


def test_reset_puts_v_curr_into_the_history_and_a_continuing_frame_reads_the_stored_v_fin():
    torch.manual_seed(0)
    model, dm = _model_and_dm()
    model.eval()
    calls = _capture(model.scene.agg)
    set_stream_stage(model, "val")
    frames = [_batch(dm, [i], "val") for i in range(2)]  # one val scene, frames 0 and 1
    assert bool(frames[0].is_sequence_start[0]) and not bool(frames[1].is_sequence_start[0])
    with torch.no_grad():
        first = model(frames[0]).scene.features
        (v_curr, v_hist, _, reset), out = calls[-1]
        assert reset.tolist() == [True]
        assert torch.equal(v_hist, v_curr) and torch.equal(out.warped, v_curr)  # the history is V_curr, unwarped
        stored = model.scene.history._stores["val"][0].value
        assert torch.equal(stored, first[0]) and not stored.requires_grad  # V_fin, detached
        model(frames[1])
        (v_curr2, v_hist2, motion, reset2), out2 = calls[-1]
        assert reset2.tolist() == [False] and torch.equal(v_hist2[0], first[0])
        assert not torch.allclose(motion[0], torch.eye(4, dtype=motion.dtype))  # the ego moved: warped, not copied
        # a gap above max_gap_s restarts the stream: V_curr again
        model.scene.history.update(frames[0], first)  # frame 0 stored again
        late = _batch(dm, [1], "val")
        late.timestamp = late.timestamp + 2.5
        model(late)
        (v_curr3, _, _, reset3), out3 = calls[-1]
        assert reset3.tolist() == [True] and torch.equal(out3.warped, v_curr3)


def test_state_is_per_slot_a_slot_predicts_the_same_alone_and_beside_another_scene():
    torch.manual_seed(0)
    model, dm = _model_and_dm()
    model.eval()
    pair = [_batch(dm, [0, 3]), _batch(dm, [1, 4])]  # slot 0: scene 0 frames 0, 1; slot 1: scene 1 frames 0, 1
    alone = [_batch(dm, [0]), _batch(dm, [1])]
    with torch.no_grad():
        set_stream_stage(model, "train")
        for b in pair:
            both = model(b).scene.features
        slots = model.scene.history.slots("train")
        assert [s[0] for s in slots.values()] == [pair[1].scene[0], pair[1].scene[1]]
        assert pair[1].scene[0] != pair[1].scene[1]
        stored = model.scene.history._stores["train"]
        assert not torch.equal(stored[0].value, stored[1].value)
        set_stream_stage(model, "test")  # another stage: its own store, the train store is left alone
        for b in alone:
            single = model(b).scene.features
        assert model.scene.history.slots("train") == slots
    torch.testing.assert_close(single[0], both[0], rtol=1e-4, atol=1e-5)


def _validate(model, dm):
    trainer = L.Trainer(accelerator="cpu", logger=False, enable_checkpointing=False, enable_progress_bar=False)
    trainer.validate(model, datamodule=dm, verbose=False)
    return dict(model.last_results["val"])


def test_validation_over_a_whole_sequence_in_order_gives_the_same_metrics_twice():
    torch.manual_seed(0)
    model, dm = _model_and_dm("stream_agg", "data.frames_per_scene=3", "data.batch_size=1")
    first = _validate(model, dm)
    # leave a stale stream in the validation store: the next run must reset at the sequence start anyway
    set_stream_stage(model, "val")
    model.eval()
    with torch.no_grad():
        model(_batch(dm, [2], "val"))
    second = _validate(model, dm)
    assert "mIoU" in first and first["mIoU"] == first["mIoU"]
    assert first.keys() == second.keys()
    assert all(
        first[k] == second[k] or (first[k] != first[k] and second[k] != second[k]) for k in first
    )  # NaN: no voxel


def test_aux_losses_only_in_training_and_a_missing_head_is_named():
    torch.manual_seed(0)
    model, dm = _model_and_dm()
    batch = _batch(dm, [0, 3])
    out = model(batch)
    assert out.extras["duocc_stream/occupied_logits"].shape == (2, 20, 20, 8)
    assert out.extras["duocc_stream/forecast_logits"].shape == (2, 18, 20, 20, 8)
    model.eval()
    with torch.no_grad():
        out = model(batch)
        assert not out.extras and set(model.losses(batch, out)) == {"depth/depth", "occupancy/voxel_ce"}
    broken, dm = _model_and_dm("stream_agg", "model.scene.occupied_head=false")
    with pytest.raises(ValueError, match="occupied_head: true"):
        broken.losses(batch, broken(batch))


def test_stacking_keeps_the_k_previous_v_curr_with_their_poses():
    torch.manual_seed(0)
    model, dm = _model_and_dm("stacking", "model.scene.num_history=2")
    model.eval()
    fpn = _capture(model.scene.fpn)
    set_stream_stage(model, "val")
    with torch.no_grad():
        for i in range(2):
            model(_batch(dm, [i], "val"))
    entry = model.scene.history._stores["val"][0].value
    assert entry["features"].shape == (2, 32, 10, 10, 4) and entry["poses"].dtype == torch.float64
    assert torch.equal(entry["features"][0], fpn[1][1][0]) and torch.equal(entry["features"][1], fpn[0][1][0])
    frames = [_batch(dm, [i], "val") for i in range(2)]
    assert torch.equal(entry["poses"][0], frames[1].ego_to_global[0].double())
    assert torch.equal(entry["poses"][1], frames[0].ego_to_global[0].double())
