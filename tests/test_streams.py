"""Stream state: per-slot resets, the reset hook, stage separation, detaching, checkpoints; the stateful
``dense_voxels_history`` scene (warp + blend with known values); the data.sequential check."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch import nn

from occplug.cli import main
from occplug.components.stateful import DenseVoxelsHistory
from occplug.geometry import GridSpec, make_pose, rotation_z
from occplug.interfaces import Lifted
from occplug.streams import StreamStages, StreamState, check_streaming, find_streams, set_stream_stage
from occplug.testing import hand_batch

BASELINE = str(Path(__file__).resolve().parents[1] / "configs" / "baseline.yaml")

GRID = GridSpec((-2.0, -2.0, 0.0, 2.0, 2.0, 1.0), 0.5)  # 8 x 8 x 2


def frames(scene, indices, times=None, starts=None, poses=None):
    """A hand batch of one frame per slot: ``scene`` (str or per slot), frame indices, timestamps."""
    b = len(indices)
    scenes = [scene] * b if isinstance(scene, str) else list(scene)
    times = [0.5 * i for i in indices] if times is None else times
    starts = [i == 0 for i in indices] if starts is None else starts
    fields = {
        "scene": scenes,
        "frame_index": torch.tensor(indices),
        "timestamp": torch.tensor(times, dtype=torch.float64),
        "is_sequence_start": torch.tensor(starts),
        "token": [f"{s}-{i}" for s, i in zip(scenes, indices, strict=False)],
    }
    if poses is not None:
        fields["ego_to_global"] = poses
    return hand_batch(b, **fields)


def test_each_slot_resets_on_start_scene_change_frame_jump_and_time_gap():
    state = StreamState(max_gap_s=1.0)
    first = frames("a", [0, 3, 5, 7, 9, 11])
    state.update(first, {"x": torch.arange(6.0)[:, None] + 1})
    # slot: 0 continues; 1 sequence start; 2 other scene; 3 frame jump (7 -> 9); 4 time gap (4.5 s -> 6 s);
    # 5 same frame again (no time step)
    nxt = frames(
        ["a", "a", "b", "a", "a", "a"],
        [1, 4, 6, 9, 10, 11],
        times=[0.5, 2.0, 3.0, 4.5, 6.0, 5.5],
        starts=[False, True, False, False, False, False],
    )
    read = state.get(nxt, {"x": torch.full((6, 1), -1.0)})
    assert read.reset.tolist() == [False, True, True, True, True, True]
    assert read.value["x"][:, 0].tolist() == [1.0, 0.0, 0.0, 0.0, 0.0, 0.0]  # default reset: zeros
    assert read.dt.tolist() == [0.5, 0, 0, 0, 0, 0]
    # without the time check the gap no longer resets; max_frame_step 2 lets the 7 -> 9 jump through
    loose = StreamState(max_gap_s=None, max_frame_step=2)
    loose.update(first, torch.arange(6.0))
    assert loose.get(nxt, torch.zeros(6)).reset.tolist() == [False, True, True, False, False, True]


def test_training_cuts_continuing_slots_at_the_given_rate_and_evaluation_never_does():
    n = 4000
    first, nxt = frames("a", [0] * n), frames("a", [1] * n)
    state = StreamState(train_cut_prob=0.25)
    torch.manual_seed(0)
    state.update(first, torch.arange(float(n)))
    read = state.get(nxt, torch.full((n,), -1.0))
    rate = read.reset.float().mean().item()
    assert 0.22 < rate < 0.28  # binomial std 0.007
    # a cut slot gets on_reset (zeros), a kept one its stored value; dt and motion follow the cut
    assert torch.equal(read.value[read.reset], torch.zeros(int(read.reset.sum())))
    assert torch.equal(read.value[~read.reset], torch.arange(float(n))[~read.reset])
    assert (read.dt[read.reset] == 0).all() and (read.dt[~read.reset] == 0.5).all()
    torch.manual_seed(0)
    assert torch.equal(state.get(nxt, torch.full((n,), -1.0)).reset, read.reset)  # seeded: repeatable
    # no cut without gradients (prediction outside Lightning) nor in the val store
    with torch.no_grad():
        assert not state.get(nxt, torch.zeros(n)).reset.any()
    state.set_stage("val")
    state.update(first, torch.arange(float(n)))
    assert not state.get(nxt, torch.zeros(n)).reset.any()
    # a sequence start stays a reset whatever is drawn
    state.set_stage("train")
    starts = frames("a", [1] * n, starts=[True] * n)
    assert state.get(starts, torch.zeros(n)).reset.all()
    for bad in (-0.1, 1.0):
        with pytest.raises(ValueError, match=r"train_cut_prob must be in \[0, 1\)"):
            StreamState(train_cut_prob=bad)


def test_reset_hook_decides_what_a_reset_puts_in_and_nested_structures_round_trip():
    state = StreamState(on_reset=lambda cur: {"vol": cur["vol"] * 2, "bank": [cur["bank"][0] + 1]})
    cur = {"vol": torch.ones(2, 3, 2), "bank": [torch.zeros(2, 4)]}
    read = state.get(frames("a", [0, 0]), cur)
    assert torch.equal(read.value["vol"], torch.full((2, 3, 2), 2.0)) and torch.equal(
        read.value["bank"][0], torch.ones(2, 4)
    )
    stored = {"vol": torch.randn(2, 3, 2, requires_grad=True), "bank": [torch.randn(2, 4)]}
    state.update(frames("a", [0, 4]), stored)
    read = state.get(frames("a", [1, 9], starts=[False, False]), cur)
    assert read.reset.tolist() == [False, True]
    assert torch.equal(read.value["vol"][0], stored["vol"][0].detach()) and torch.equal(
        read.value["vol"][1], cur["vol"][1] * 2
    )
    assert torch.equal(read.value["bank"][0][0], stored["bank"][0][0])
    assert not read.value["vol"].requires_grad  # detached: no gradient across frames


def test_prev_to_current_is_the_ego_motion_between_the_stored_and_the_current_frame():
    state = StreamState()
    p0 = make_pose(rotation_z(0.3).double(), torch.tensor([10.0, 5.0, 0.0], dtype=torch.float64))
    p1 = make_pose(rotation_z(0.5).double(), torch.tensor([12.0, 6.0, 0.0], dtype=torch.float64))
    state.update(frames("a", [0], poses=p0[None]), torch.zeros(1))
    read = state.get(frames("a", [1], poses=p1[None]), torch.zeros(1))
    point_global = torch.tensor([13.0, 4.0, 1.0, 1.0], dtype=torch.float64)
    in_prev, in_cur = torch.linalg.inv(p0) @ point_global, torch.linalg.inv(p1) @ point_global
    torch.testing.assert_close(read.prev_to_current[0] @ in_prev, in_cur)
    fresh = state.get(frames("a", [0], poses=p1[None]), torch.zeros(1))
    assert torch.equal(fresh.prev_to_current[0], torch.eye(4, dtype=torch.float64))


def test_each_stage_has_its_own_store_and_checkpointing_is_opt_in():
    state = StreamState()
    state.update(frames("train-scene", [0]), torch.tensor([7.0]))
    state.set_stage("val")
    state.update(frames("val-scene", [0]), torch.tensor([3.0]))
    assert state.get(frames("val-scene", [1], starts=[False]), torch.zeros(1)).value.tolist() == [3.0]
    state.set_stage("train")  # the validation pass left the training state alone
    read = state.get(frames("train-scene", [1], starts=[False]), torch.zeros(1))
    assert read.reset.tolist() == [False] and read.value.tolist() == [7.0]
    assert state.slots("train") == {0: ("train-scene", 0, 0.0)}
    state.clear("val")
    assert state.slots("val") == {} and state.slots("train")

    copy = StreamState()
    copy.load_state_dict(state.state_dict())
    assert copy.slots("train") == state.slots("train")

    class Holder(nn.Module):
        def __init__(self, persistent):
            super().__init__()
            self.inner = nn.Module()
            self.inner.stream = StreamState(persistent=persistent)

    for persistent in (False, True):
        holder = Holder(persistent)
        holder.inner.stream.update(frames("s", [0]), torch.ones(1))
        assert "inner.stream" not in str(holder.state_dict().keys())  # never in the module's state_dict
        ckpt: dict = {}
        StreamStages().on_save_checkpoint(None, holder, ckpt)
        assert (StreamStages.KEY in ckpt) is persistent
        if persistent:
            other = Holder(True)
            StreamStages().on_load_checkpoint(None, other, ckpt)
            assert other.inner.stream.slots() == {0: ("s", 0, 0.0)}


def test_stream_stages_callback_points_every_state_at_the_running_loop():
    holder = nn.Sequential(DenseVoxelsHistory(2, 2, 0), DenseVoxelsHistory(2, 2, 0))
    states = [s for _, s in find_streams(holder)]
    assert [n for n, _ in find_streams(holder)] == ["0.history", "1.history"]
    cb = StreamStages()
    cb.on_validation_batch_start(None, holder, None, 0)
    assert {s.stage for s in states} == {"val"}
    states[0].update(frames("v", [0]), torch.ones(1))
    cb.on_validation_epoch_end(None, holder)  # an evaluation store is emptied when its loop ends
    assert states[0].slots("val") == {}
    cb.on_train_batch_start(None, holder, None, 0)
    assert {s.stage for s in states} == {"train"}
    for hook, stage in ((cb.on_test_batch_start, "test"), (cb.on_predict_batch_start, "predict")):
        hook(None, holder, None, 0)
        assert {s.stage for s in states} == {stage}


# ---------------------------------------------------------------------------------------------- the component


def scene_module(weight=0.25, reset="current"):
    torch.manual_seed(0)
    return DenseVoxelsHistory(3, 4, num_blocks=0, history_weight=weight, reset=reset).eval()


def volume(seed):
    return torch.randn(1, 3, *GRID.shape, generator=torch.Generator().manual_seed(seed))


def test_first_frame_is_the_current_volume_and_identity_motion_blends_in_place():
    m = scene_module()
    with torch.no_grad():
        v0 = m(Lifted(volume(0), GRID), frames("a", [0])).features
        cur1 = DenseVoxelsHistory.__mro__[1].forward(m, Lifted(volume(1), GRID), frames("a", [1])).features
        v1 = m(Lifted(volume(1), GRID), frames("a", [1], starts=[False])).features
    plain = DenseVoxelsHistory.__mro__[1].forward(m, Lifted(volume(0), GRID), frames("a", [0])).features
    assert torch.equal(v0, plain)  # reset "current": F_0 = V_0 exactly
    torch.testing.assert_close(v1, 0.75 * cur1 + 0.25 * v0, rtol=0, atol=1e-6)  # same pose: warp is the identity


def test_history_moves_with_the_ego_one_voxel_forward():
    m = scene_module(weight=0.5, reset="zeros")
    step = make_pose(torch.eye(3, dtype=torch.float64), torch.tensor([0.5, 0.0, 0.0], dtype=torch.float64))
    with torch.no_grad():
        f0 = m(Lifted(volume(0), GRID), frames("a", [0])).features
        cur1 = DenseVoxelsHistory.__mro__[1].forward(m, Lifted(volume(1), GRID), frames("a", [1])).features
        f1 = m(Lifted(volume(1), GRID), frames("a", [1], starts=[False], poses=step[None])).features
    assert torch.equal(
        f0, 0.5 * DenseVoxelsHistory.__mro__[1].forward(m, Lifted(volume(0), GRID), frames("a", [0])).features
    )
    warped = (f1 - 0.5 * cur1) / 0.5
    # the ego moved +0.5 m (one voxel) in x: current voxel i shows what the previous frame had at i + 1
    torch.testing.assert_close(warped[:, :, :-1], f0[:, :, 1:], rtol=0, atol=1e-5)
    torch.testing.assert_close(warped[:, :, -1], torch.zeros_like(warped[:, :, -1]), rtol=0, atol=1e-6)


def test_a_frame_predicts_the_same_alone_and_after_another_scene():
    def run(sequence):
        m = scene_module()
        out = {}
        with torch.no_grad():
            for scene, index in sequence:
                batch = frames(scene, [index])
                out[(scene, index)] = m(Lifted(volume(hash((scene, index)) % 1000), GRID), batch).features
        return out

    alone = run([("b", 0), ("b", 1), ("b", 2)])
    after = run([("a", 0), ("a", 1), ("b", 0), ("b", 1), ("b", 2)])
    for key, value in alone.items():
        assert torch.equal(value, after[key]), key
    assert not torch.equal(alone[("b", 1)], alone[("b", 0)])


def test_learnable_weight_gets_a_gradient_through_a_continuing_slot():
    m = DenseVoxelsHistory(3, 4, num_blocks=0, learn_weight=True)
    m(Lifted(volume(0), GRID), frames("a", [0]))
    m(Lifted(volume(1), GRID), frames("a", [1], starts=[False])).features.sum().backward()
    assert m.weight_logit.grad is not None and m.weight_logit.grad.abs() > 0


def test_stateful_model_needs_sequential_data(tmp_path, capsys):
    m = nn.ModuleDict({"scene": DenseVoxelsHistory(2, 2, 0)})

    class Data:
        sequential = False

    try:
        check_streaming(m, Data())
    except ValueError as exc:
        assert str(exc).startswith("data.sequential: model.scene (DenseVoxelsHistory) is stateful")
    else:
        raise AssertionError("no error")
    Data.sequential = True
    check_streaming(m, Data())
    set_stream_stage(m, "test")
    assert m["scene"].history.stage == "test"

    run = tmp_path / "run"
    code = main(
        ["fit", "-c", BASELINE, "data.preset=tiny", "model.scene.type=dense_voxels_history", "--run-dir", str(run)]
    )
    err = capsys.readouterr().err
    assert code == 2 and err.strip().count("\n") == 0 and "data.sequential" in err and "Traceback" not in err
    assert not run.exists()


def test_sanity_check_and_mid_epoch_validation_leave_the_training_stream_alone():
    import lightning as L

    from occplug.run.runner import build_run, load_config

    cfg = load_config(
        [BASELINE],
        [
            "data.preset=tiny",
            "model.scene.type=dense_voxels_history",
            "data.sequential=true",
            "data.train_scenes=1",
            "data.frames_per_scene=3",
            "data.batch_size=1",
        ],
    )
    dm, model = build_run(cfg)
    state = model.scene.history
    seen = []
    original = state.get

    def spy(batch, current):
        read = original(batch, current)
        seen.append((state.stage, int(batch.frame_index[0]), bool(read.reset[0])))
        return read

    state.get = spy
    trainer = L.Trainer(
        accelerator="cpu",
        max_steps=3,
        val_check_interval=1,
        num_sanity_val_steps=1,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    trainer.fit(model, datamodule=dm)
    train = [(f, r) for stage, f, r in seen if stage == "train"]
    assert train == [(0, True), (1, False), (2, False)]  # continued across the validations in between
    val = [(f, r) for stage, f, r in seen if stage == "val"]
    assert val[0] == (0, True) and len(val) == 1 + 3 * 3  # sanity check, then 3 validations of 3 frames
    assert val[1:4] == [(0, True), (1, False), (2, False)]


def test_config_validate_names_a_stateful_component_without_sequential_data(capsys):
    from occplug.cli import main

    baseline = str(Path(__file__).resolve().parents[1] / "configs" / "baseline.yaml")
    assert main(["config", "validate", "-c", baseline, "model.scene.type=dense_voxels_history"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        "error: data.sequential: model.scene (dense_voxels_history) is stateful (it carries features from frame to "
        "frame) and needs data.sequential: true"
    )
    assert main(["config", "validate", "-c", baseline, "model.scene.type=dense_voxels_history", "data.sequential=true"]) == 0
