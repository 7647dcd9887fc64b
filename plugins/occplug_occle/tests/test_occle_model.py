"""OccLE as an occplug model: builds from its configs, trains, predicts, runs the three phases (tiny world)."""

import dataclasses
import json

import pytest
import torch

from occplug.run import runner
from occplug.testing import run_config

# 16 x 16 x 8 voxels in front of the ego (the recipe's 32 x 32 x 8 shrunk for test speed)
SMALL = ["grid.range=[0.0,-6.4,-1.0,12.8,6.4,5.4]", "model.scene.mamba_channels=[16,24]"]


def _model_and_batch(*overrides):
    cfg = runner.load_config(["occle/base", "occplug/trainer/debug"], [*SMALL, *overrides])
    dm, model = runner.build_run(cfg)
    dataset = dm.dataset("train")
    batch = dm.collate([dataset[i] for i in range(2)])
    return model, batch


def _loss(model, batch):
    losses = model.losses(batch, model(batch))
    return torch.stack(list(losses.values())).sum(), losses


def test_base_trains_without_nan_and_the_loss_falls_on_one_batch():
    torch.manual_seed(0)
    model, batch = _model_and_batch()
    assert set(model.heads) == {"occupancy", "lidar_semantic", "geometry", "image_semantic", "projection"}
    _, terms = _loss(model, batch)
    expected = {"semantic/image_ce", "semantic/lidar_ce", "fusion/occ_ce", "fusion/projection_ce", "geometry/geo_ce"}
    assert expected <= set(terms)
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3)
    history = []
    for _ in range(5):
        loss, _ = _loss(model, batch)
        assert torch.isfinite(loss)
        opt.zero_grad()
        loss.backward()
        assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
        opt.step()
        history.append(float(loss.detach()))
    assert history[-1] < history[0]
    model.eval()
    pred = model.predict_occupancy(batch)
    assert pred.shape == (2, 16, 16, 8) and pred.dtype == torch.int64
    assert 0 <= int(pred.min()) and int(pred.max()) < model.num_classes


@pytest.mark.parametrize(
    "switch",
    [
        "model.scene.semantic=false",
        "model.scene.geometric=false",
        "model.scene.projection=false",
        "model.scene.geometry=conv3d",
        "model.heads.projection.mode=distance",
    ],
)
def test_ablation_switch_builds_and_trains_one_step(switch):
    torch.manual_seed(0)
    model, batch = _model_and_batch(switch, "model.scene.fusion=conv")
    loss, terms = _loss(model, batch)
    loss.backward()
    assert torch.isfinite(loss)
    if "semantic=false" in switch:
        assert not any(k.startswith("semantic/") for k in terms)
        assert "semantic_branch" not in dict(model.scene.named_children())
    if "geometric=false" in switch:
        assert "geometry/geo_ce" not in terms
    if "projection=false" in switch:
        assert "fusion/projection_ce" not in terms
    assert model.predict_occupancy(batch).shape == (2, 16, 16, 8)


def test_fusion_without_voxel_labels_reads_none():
    """``occupancy_weight: 0`` (Table C.2, no voxel labels): only ``l_ce(y, s̄)`` is left of ``l_fus``, and the
    loss does not change when every voxel label does."""
    torch.manual_seed(0)
    model, batch = _model_and_batch("model.scene.fusion=conv", "model.supervision.fusion.occupancy_weight=0")
    model.eval()
    with torch.no_grad():
        outputs = model(batch)
        terms = model.supervision["fusion"](batch, outputs)
        assert set(terms) == {"projection_ce"}
        batch.voxel_labels = torch.randint_like(batch.voxel_labels, 0, 18)
        again = model.supervision["fusion"](batch, outputs)
    assert torch.equal(terms["projection_ce"], again["projection_ce"])
    _, all_terms = _loss(model, batch)
    assert not any(k.startswith("fusion/occ_") for k in all_terms)


def test_geometry_head_gives_k_class_logits_with_two_class_probabilities():
    model, batch = _model_and_batch("model.scene.fusion=conv")
    model.eval()
    with torch.no_grad():
        out = model(batch).heads["geometry"]
    two = out["geometry"].softmax(1)
    k = out["logits"].softmax(1)
    free, occ = model.heads["geometry"].free_label, model.heads["geometry"].occupied_label
    assert torch.allclose(k[:, free], two[:, 0], atol=1e-6) and torch.allclose(k[:, occ], two[:, 1], atol=1e-6)
    assert set(out["logits"].argmax(1).unique().tolist()) <= {free, occ}


def test_three_phases_run_and_mark_done(tmp_path):
    run = tmp_path / "run"
    metrics = run_config("occle/three_phase_10pct", run_dir=run, overrides=[*SMALL, "trainer.max_steps=1"])
    for phase in ("semantic", "teacher", "student", "fusion"):
        assert (run / phase / "DONE").is_file(), phase
    assert (run / "pseudo_labels" / "teacher.geometry.unlabelled" / "DONE").is_file()
    assert json.loads((run / "metrics.json").read_text())["final_phase"] == "fusion"
    assert metrics["IoU"] == metrics["IoU"]  # computed, not NaN
    # phase III trains with the geometric branch frozen at the student's weights
    student = torch.load(run / "student" / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
    fusion = torch.load(run / "fusion" / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
    keys = [k for k in student if k.startswith("scene.geometric_branch.") and student[k].is_floating_point()]
    assert keys and all(torch.equal(student[k], fusion[k]) for k in keys)


def test_two_frames_fuses_the_previous_frame_in_the_geometric_branch():
    """``occle/two_frames``: the cross-plane branch reads [previous, current]; the previous frame matters to G only
    through the model's ``input_history`` (the semantic branch reads the current frame)."""
    torch.manual_seed(0)
    cfg = runner.load_config(["occle/two_frames", "occplug/trainer/debug"], ["data.preset=tiny", *SMALL])
    dm, model = runner.build_run(cfg)
    data = dm.dataset("train")
    batch = dm.collate([data[i] for i in (1, 2)])
    assert model.scene.geometric_branch.num_frames == 2
    loss, _ = _loss(model, batch)
    loss.backward()
    assert torch.isfinite(loss)
    model.eval()
    with torch.no_grad():
        out = model(batch)
        past = batch.adjacent[-1]
        other = dataclasses.replace(past, points=[p.flip(0)[: len(p) // 2] for p in past.points])
        changed = model(dataclasses.replace(batch, adjacent={-1: other}))
    assert float((changed.heads["geometry"]["logits"] - out.heads["geometry"]["logits"]).abs().max()) > 1e-5
    torch.testing.assert_close(changed.scene.lidar_semantic, out.scene.lidar_semantic)
    model.input_history = []
    with pytest.raises(ValueError, match=r"^occle_scene history reads past frames \[-1\]; set model.input_history"):
        model(batch)


def test_two_frames_composes_with_the_phased_recipe():
    from occplug.config import phase_specs, validate
    from occplug.plugins import get_registry

    cfg = runner.load_config(["occle/three_phase_10pct", "occle/two_frames"])
    validate(cfg, get_registry())
    specs = phase_specs(cfg)
    assert [s.name for s in specs] == ["semantic", "teacher", "student", "fusion"]
    for spec in specs:
        assert spec.config["model"]["input_history"] == [-1] and spec.config["model"]["scene"]["history"] == [-1]
        assert spec.config["data"]["adjacent_offsets"] == [-1] and spec.config["data"]["label_fraction"] == 0.1


def test_semantic_checkpoint_gives_the_same_loss_and_gradients_and_keeps_less_of_the_unet():
    """``semantic_checkpoint`` recomputes the LiDAR UNet and the mix in backward: the step's loss and
    every parameter's gradient equal the plain model's, and the UNet keeps nothing for backward."""
    from occplug.run.memory import SavedTensorProfile

    results = {}
    for flag in (False, True):
        torch.manual_seed(0)
        model, batch = _model_and_batch(f"model.scene.semantic_checkpoint={str(flag).lower()}")
        if flag:
            model.load_state_dict(results[False][0])
        with SavedTensorProfile(model) as profile:
            loss, _ = _loss(model, batch)
        loss.backward()
        grads = {k: p.grad.clone() for k, p in model.named_parameters() if p.grad is not None}
        unet = sum(v for k, v in profile.saved.items() if k.startswith("scene.semantic_branch"))
        results[flag] = ({k: v.detach().clone() for k, v in model.state_dict().items()}, loss.detach(), grads, unet)
    (_, loss_plain, grads_plain, unet_plain), (_, loss_ckpt, grads_ckpt, unet_ckpt) = results[False], results[True]
    assert torch.allclose(loss_plain, loss_ckpt, rtol=1e-6, atol=0)
    assert grads_plain.keys() == grads_ckpt.keys() and any(k.startswith("scene.semantic_branch") for k in grads_plain)
    for key, grad in grads_plain.items():
        assert torch.allclose(grad, grads_ckpt[key], rtol=1e-5, atol=1e-7), key
    assert unet_plain > 0 and unet_ckpt == 0


@pytest.mark.parametrize(("phase", "compute", "skipped"), [
    ("semantic", "semantic", ("scene.geometric_branch", "scene.fusion")),
    ("teacher", "geometric", ("scene.semantic_branch", "scene.fusion")),
])  # fmt: skip
def test_computing_one_branch_gives_the_phases_loss_and_gradients_and_runs_nothing_else(phase, compute, skipped):
    """``compute: semantic`` (Phase I) and ``compute: geometric`` (the teacher): the phase's loss and every gradient
    equal the full forward's, the modules no loss reads keep nothing for backward, and the heads on the grids not
    run give nothing."""
    import copy

    from occplug.config import phase_specs
    from occplug.run.memory import SavedTensorProfile

    cfg = runner.load_config(["occle/three_phase_10pct", "occplug/trainer/debug"], SMALL)
    spec = next(s for s in phase_specs(cfg) if s.name == phase)
    results = {}
    for mode in ("all", compute):
        config = copy.deepcopy(spec.config)
        config["model"]["scene"]["compute"] = mode
        torch.manual_seed(0)
        dm = runner.build_datamodule(config)
        model = runner.build_model(config, dm)
        if mode != "all":
            model.load_state_dict(results["all"][0])
        dataset = dm.dataset("train")
        batch = dm.collate([dataset[i] for i in range(min(2, len(dataset)))])
        with SavedTensorProfile(model) as profile:
            outputs = model(batch)
            losses = model.losses(batch, outputs)
        loss = torch.stack(list(losses.values())).sum()
        loss.backward()
        grads = {k: p.grad.clone() for k, p in model.named_parameters() if p.grad is not None}
        kept = {name: sum(v for k, v in profile.saved.items() if k.startswith(name)) for name in skipped}
        state = {k: v.detach().clone() for k, v in model.state_dict().items()}
        results[mode] = (state, loss.detach(), grads, kept, outputs)
    _, loss_all, grads_all, kept_all, _ = results["all"]
    _, loss_one, grads_one, kept_one, outputs = results[compute]
    assert torch.allclose(loss_all, loss_one, rtol=1e-6, atol=0)
    assert grads_all.keys() == grads_one.keys() and grads_all
    for key, grad in grads_all.items():
        assert torch.allclose(grad, grads_one[key], rtol=1e-5, atol=1e-7), key
    assert all(kept_all[name] > 0 for name in skipped) and all(kept_one[name] == 0 for name in skipped)
    assert outputs.heads["occupancy"] == {} and outputs.heads["projection"] == {}
    assert outputs.scene.features is None


def test_compute_names_a_branch_that_is_on():
    from occplug_occle.scene import OccleScene

    grid = {"range": [0.0, -6.4, -1.0, 12.8, 6.4, 5.4], "voxel_size": 0.8}
    with pytest.raises(ValueError, match="compute: geometric runs the geometric branch alone, which is switched off"):
        OccleScene(32, grid, geometric=False, compute="geometric")
    with pytest.raises(ValueError, match="compute must be 'all', 'semantic' or 'geometric'"):
        OccleScene(32, grid, compute="fusion")


def test_the_semantickitti_recipe_runs_in_each_phase_only_what_its_losses_read():
    """``occle/semantickitti``: Phase I computes the semantic branch, the teacher and the student the geometric one,
    Phase III everything; and each phase's losses read only what it computes."""
    from occplug.config import phase_specs

    cfg = runner.load_config(["occle/semantickitti"], ["data.root=/nonexistent"])
    compute = {s.name: s.config["model"]["scene"].get("compute", "all") for s in phase_specs(cfg)}
    assert compute == {"semantic": "semantic", "teacher": "geometric", "student": "geometric", "fusion": "all"}
    losses = {s.name: set(s.config["model"]["supervision"]) for s in phase_specs(cfg)}
    assert losses["semantic"] == {"semantic"}
    assert losses["teacher"] == losses["student"] == {"geometry"}
    heads = {s.name: s.config["model"]["occupancy_head"] for s in phase_specs(cfg)}
    assert heads["semantic"] == "lidar_semantic" and heads["teacher"] == heads["student"] == "geometry"
