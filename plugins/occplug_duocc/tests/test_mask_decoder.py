"""DuOcc's auxiliary mask decoder (``duocc_mask``, training only): matching, groups, masking, training.

Its focal and dice costs and losses are the core's (``tests/nn/test_losses.py``)."""

import dataclasses

import pytest
import torch
import torch.nn.functional as F

from occplug.config import ConfigError
from occplug.interfaces import DenseVoxelScene, ModelOutputs
from occplug.run import runner
from occplug.streams import set_stream_stage
from occplug.testing import check_component, label_grid, make_tiny_batch
from occplug_duocc.scene import StreamVoxelScene, coarse_grid
from occplug_duocc.supervision.mask_decoder import (
    OCC3D_GROUP_SPLIT,
    DuOccMask,
    MaskDecoder,
    MaskDecoderOutput,
    group_lookup,
    match_masks,
)

SMALL = ["grid.range=[-8.0,-8.0,-1.0,8.0,8.0,5.4]", "model.encoder.out_channels=16", "model.encoder.width=16"]
TINY = dict(in_channels=8, num_queries=4, num_groups=3, channels=16, heads=2, points=2, ffn_hidden=32, mask_hidden=32)


def _source(**kwargs):
    torch.manual_seed(0)
    return DuOccMask(
        grid=label_grid(make_tiny_batch()),
        **{"num_classes": 18, "scene_downsample": 2, **TINY, "dropout": 0.0, **kwargs},
    )


def _outputs(source, batch, seed=1):
    gen = torch.Generator().manual_seed(seed)
    volume = torch.randn(
        len(batch), source.decoder.layers[0].cross.value_proj.in_features, *source.grid.shape, generator=gen
    )
    return ModelOutputs(None, None, StreamVoxelScene(volume, source.grid, source.label_grid), {}, lambda *a, **k: None)


#: The public code's cfg ``group_split`` (projects/configs/DuOcc.py): label id (free = 17 last) -> coarse class,
#: the last entry (free) the group's no-object index.
CODE_GROUP_SPLIT = [
    [0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 1, 2],
    [0, 0, 1, 2, 0, 3, 4, 0, 0, 5, 0, 0, 0, 0, 0, 0, 0, 6],
    [0, 1, 0, 0, 2, 0, 0, 3, 4, 0, 5, 0, 0, 0, 0, 0, 0, 6],
    [0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 2, 3, 0, 0, 4],
    [0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 2, 3, 4],
]


def test_group_tables_full_set_code_split_and_a_bad_split():
    full = group_lookup(18, 17, None)
    assert full.tolist() == list(range(18))  # Occ3D: free (17) is already the last id = group 0's no-object
    assert [len(g) for g in OCC3D_GROUP_SPLIT] == [2, 6, 6, 4, 4]  # the public code's group_split
    assert [group_lookup(18, 17, split).tolist() for split in OCC3D_GROUP_SPLIT] == CODE_GROUP_SPLIT
    source = _source(num_groups=6)
    assert source.lookup.tolist() == [list(range(18)), *CODE_GROUP_SPLIT]
    assert source.decoder.group_classes == (17, 2, 6, 6, 4, 4)  # the code's group_classes
    kitti = group_lookup(4, 0, None)  # free first (SemanticKITTI-like): the others shift down
    assert kitti.tolist() == [3, 0, 1, 2]
    with pytest.raises(ValueError, match="exactly once"):
        group_lookup(18, 17, [list(range(11)), list(range(10, 17))])  # 10 twice
    with pytest.raises(ValueError, match="exactly once"):
        group_lookup(18, 17, [list(range(11))])  # 11..16 missing
    with pytest.raises(ValueError, match="num_groups 7"):
        _source(num_groups=7)


def test_coarse_group_weight_defaults_to_the_codes_one_over_groups_minus_one():
    assert _source(num_groups=3).coarse_group_weight == pytest.approx(1 / 2)
    assert _source(num_groups=6).coarse_group_weight == pytest.approx(1 / 5)  # the code's 6 groups: 1/5
    assert _source(num_groups=1).coarse_group_weight == 0.0  # no coarse group to weigh
    assert _source(num_groups=3, coarse_group_weight=0.3).coarse_group_weight == 0.3  # explicit wins


def _reference_group_loss(cls_logits, masks, coarse, keep):
    """An independent Mask2Former group loss (scipy's Hungarian on the explicit cost, dense per-pair formulas).

    ``cls_logits (B, Q, K + 1)``, ``masks (B, Q, X, Y, Z)``, ``coarse (B, X, Y, Z)`` (``K`` = free),
    ``keep (B, X, Y, Z)``. Returns unweighted ``(ce, focal, dice)``: CE the no-object-0.1-weighted mean over the
    queries of samples with visible voxels; focal (voxel mean per mask) and dice (eps 1) summed over the matched
    pairs of the batch and divided by their count.
    """
    from scipy.optimize import linear_sum_assignment

    def focal(logit, t):  # (..., V) logits and targets -> (...) voxel mean; alpha 0.25, gamma 2
        p = logit.sigmoid()
        pos = -0.25 * t * (1 - p) ** 2 * F.logsigmoid(logit)
        neg = -0.75 * (1 - t) * p**2 * F.logsigmoid(-logit)
        return (pos + neg).mean(-1)

    def dice(logit, t):
        p = logit.sigmoid()
        return 1 - (2 * (p * t).sum(-1) + 1) / (p.sum(-1) + t.sum(-1) + 1)

    q, k1 = cls_logits.shape[1:]
    logits, targets, focal_sum, dice_sum, matched = [], [], 0.0, 0.0, 0
    for b in range(cls_logits.shape[0]):
        if not bool(keep[b].any()):
            continue
        pred, gt = masks[b][:, keep[b]], coarse[b][keep[b]]
        labels = gt.unique()  # free (K) included: a ground-truth mask labelled with the no-object index
        gt_masks = (gt[None] == labels[:, None]).float()
        with torch.no_grad():
            cost = (
                -1.0 * cls_logits[b].softmax(-1)[:, labels]
                + 20.0 * focal(pred[:, None], gt_masks[None])
                + 1.0 * dice(pred[:, None], gt_masks[None])
            )
        rows, cols = linear_sum_assignment(cost.double().numpy())
        rows, cols = torch.as_tensor(rows), torch.as_tensor(cols)
        target = torch.full((q,), k1 - 1)
        target[rows] = labels[cols]
        logits.append(cls_logits[b])
        targets.append(target)
        focal_sum = focal_sum + focal(pred[rows], gt_masks[cols]).sum()
        dice_sum = dice_sum + dice(pred[rows], gt_masks[cols]).sum()
        matched += len(rows)
    logits, targets = torch.cat(logits), torch.cat(targets)
    weight = torch.ones(k1)
    weight[-1] = 0.1
    per_query = F.cross_entropy(logits, targets, reduction="none") * weight[targets]
    return per_query.sum() / weight[targets].sum(), focal_sum / matched, dice_sum / matched


def test_loss_equals_an_independent_reimplementation():
    groups, queries = 4, 6
    source = _source(num_groups=groups, num_queries=queries)
    batch = make_tiny_batch()
    labels = batch.voxel_labels.long().clone()
    visible = batch.mask_camera.bool()
    assert len(labels) == 2 and all(bool(v.any()) and bool((~v).any()) for v in visible)  # partly hidden samples
    gen = torch.Generator().manual_seed(3)
    ignore = visible & (torch.rand(labels.shape, generator=gen) < 0.05)
    labels[ignore] = 255
    keep = visible & (labels != 255)
    counted = source.counted(batch, labels)
    assert torch.equal(counted, keep)
    layers = [
        MaskDecoderOutput(
            [torch.randn(2, queries, int(t.max()) + 1, generator=gen) for t in source.lookup],
            torch.randn(2, groups * queries, *labels.shape[1:], generator=gen) * 2,
        )
        for _ in range(2)
    ]  # two layers, logits on the label grid
    got = source.loss(layers, labels, counted)
    safe = torch.where(keep, labels, torch.full_like(labels, 17))
    tables = [list(range(18)), *CODE_GROUP_SPLIT[: groups - 1]]
    want = {"mask_cls": 0.0, "mask_focal": 0.0, "mask_dice": 0.0}
    for out in layers:
        for g in range(groups):
            coarse = torch.as_tensor(tables[g])[safe]
            masks = out.mask_logits[:, g * queries : (g + 1) * queries]
            ce, focal, dice = _reference_group_loss(out.cls_logits[g], masks, coarse, keep)
            w = 1.0 if g == 0 else 1 / (groups - 1)  # the code's coarse-group weight
            want["mask_cls"] += w * 1.0 * ce
            want["mask_focal"] += w * 20.0 * focal
            want["mask_dice"] += w * 1.0 * dice
    assert set(got) == set(want)
    for key in want:
        torch.testing.assert_close(got[key], torch.as_tensor(want[key], dtype=torch.float32), rtol=1e-5, atol=1e-6)


def test_loss_is_float32_under_bf16_autocast():
    source = _source()
    batch = make_tiny_batch()
    outputs = _outputs(source, batch)
    full = source(batch, outputs)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        mixed = source(batch, outputs)  # the decoder runs in bf16, the loss must not
    for key in full:
        assert mixed[key].dtype == torch.float32, key
        torch.testing.assert_close(mixed[key], full[key], rtol=5e-2, atol=1e-3)
    # the loss math alone: bf16 logits give exactly the float32 loss of the same (rounded) values
    labels = batch.voxel_labels.long()
    counted = source.counted(batch, labels)
    with torch.no_grad():
        low = [
            MaskDecoderOutput([c.bfloat16() for c in out.cls_logits], out.mask_logits.bfloat16())
            for out in source.decoder(outputs.scene.features)
        ]
    high = [MaskDecoderOutput([c.float() for c in out.cls_logits], out.mask_logits.float()) for out in low]
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = source.loss(low, labels, counted)
    want = source.loss(high, labels, counted)
    for key in want:
        assert got[key].dtype == torch.float32, key
        torch.testing.assert_close(got[key], want[key], rtol=1e-5, atol=1e-6)


def test_matching_finds_the_optimal_assignment_where_greedy_does_not():
    # class cost only: greedy takes q0 -> A (0.50) then q1 -> B (0.02), total 0.52; the optimum is 0.45 + 0.48
    probs = torch.tensor([[0.50, 0.45, 0.05], [0.48, 0.02, 0.50]])
    masks, gt_masks = torch.zeros(2, 4), torch.ones(2, 4)
    qi, gi = match_masks(probs.log(), masks, torch.tensor([0, 1]), gt_masks, 1.0, 0.0, 0.0)
    assert qi.tolist() == [0, 1] and gi.tolist() == [1, 0]
    # mask costs only: query 0 draws ground truth 1, query 2 ground truth 0, query 1 matches nothing
    gt_masks = torch.tensor([[1.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.0]])
    pred = torch.tensor([[-8.0, -8.0, 8.0, 8.0], [8.0, -8.0, 8.0, -8.0], [8.0, 8.0, -8.0, -8.0]])
    qi, gi = match_masks(torch.zeros(3, 3), pred, torch.tensor([0, 2]), gt_masks)
    assert qi.tolist() == [0, 2] and gi.tolist() == [1, 0]


def test_group_self_attention_does_not_leak_across_groups():
    torch.manual_seed(0)
    grid = coarse_grid(label_grid(make_tiny_batch()), 2)
    decoder = MaskDecoder(8, grid, [17, 2, 6], num_queries=4, channels=16, heads=2, points=2, num_layers=2).eval()
    volume = torch.randn(1, 8, *grid.shape)
    with torch.no_grad():
        before = decoder(volume)[-1]
        decoder.query_feat.weight[4:8] += torch.randn(4, 16)  # group 1's queries and positions only
        decoder.query_pos.weight[4:8] += torch.randn(4, 16)
        after = decoder(volume)[-1]
    for g in (0, 2):
        assert torch.equal(before.cls_logits[g], after.cls_logits[g])
        assert torch.equal(before.mask_logits[:, 4 * g : 4 * g + 4], after.mask_logits[:, 4 * g : 4 * g + 4])
    assert not torch.allclose(before.cls_logits[1], after.cls_logits[1])
    assert [c.shape[-1] for c in before.cls_logits] == [18, 3, 7]  # each group's classes + no-object
    assert before.mask_logits.shape == (1, 12, *grid.shape)


def test_voxels_outside_the_camera_mask_do_not_affect_the_loss():
    source = _source()
    batch = make_tiny_batch()
    outputs = _outputs(source, batch)
    hidden = ~batch.mask_camera.bool()
    assert bool(hidden.any()) and bool((~hidden).any())
    torch.manual_seed(0)
    first = source(batch, outputs)
    assert set(first) == {"mask_cls", "mask_focal", "mask_dice"} and all(torch.isfinite(v) for v in first.values())
    scrambled = batch.voxel_labels.clone()
    scrambled[hidden] = torch.randint(0, 18, (int(hidden.sum()),), dtype=scrambled.dtype)
    torch.manual_seed(0)
    second = source(dataclasses.replace(batch, voxel_labels=scrambled), outputs)
    for key in first:
        assert torch.equal(first[key], second[key]), key
    # the predicted masks outside do not count either
    labels = batch.voxel_labels.long()
    counted = source.counted(batch, labels)
    layers = source.decoder(outputs.scene.features)
    base = source.loss(layers, labels, counted)
    for out in layers:
        up = torch.nn.functional.interpolate(out.mask_logits, size=labels.shape[1:], mode="trilinear")
        out.mask_logits = torch.where(counted[:, None], up, torch.full_like(up, 50.0))
    moved = source.loss(layers, labels, counted)
    for key in base:
        torch.testing.assert_close(base[key], moved[key])
    # and a visible voxel does: relabelling one changes the loss
    relabelled = batch.voxel_labels.clone()
    idx = tuple(i[0] for i in torch.nonzero(~hidden & (batch.voxel_labels == 17), as_tuple=True))
    relabelled[idx] = 4
    third = source(dataclasses.replace(batch, voxel_labels=relabelled), outputs)
    assert any(not torch.equal(first[k], third[k]) for k in first)


def test_loss_falls_on_a_fixed_batch_and_nothing_is_returned_outside_training():
    source = _source()
    batch = make_tiny_batch()
    outputs = _outputs(source, batch)
    opt = torch.optim.Adam(source.parameters(), lr=1e-2)
    history = []
    for _ in range(12):
        loss = torch.stack(list(source(batch, outputs).values())).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
        history.append(float(loss.detach()))
    assert history[-1] < 0.8 * history[0], history
    source.eval()
    assert source(batch, outputs) == {}


def test_conformance_with_a_small_decoder():
    check_component("supervision", "duocc_mask", TINY, batch=make_tiny_batch())  # in_channels: the check's width


def test_full_mask_trains_and_predicts_exactly_as_full_with_the_same_weights():
    torch.manual_seed(0)
    cfg = runner.load_config(["duocc/full_mask", "occplug/trainer/debug"], SMALL)
    dm, model = runner.build_run(cfg)
    mask = model.supervision["mask"]
    assert (mask.decoder.groups, mask.decoder.num_queries, len(mask.decoder.layers)) == (3, 8, 1)
    assert mask.weight == 1.0 and mask.training_mask == "camera"
    data = dm.dataset("train")
    batch = dm.collate([data[i] for i in (0, 3)])
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3)
    start = {k: v.clone() for k, v in mask.state_dict().items()}
    for _ in range(2):
        losses = model.losses(batch, model(batch))
        assert {"mask/mask_cls", "mask/mask_focal", "mask/mask_dice"} <= set(losses)
        opt.zero_grad()
        torch.stack(list(losses.values())).sum().backward()
        opt.step()
    assert any(not torch.equal(start[k], v) for k, v in mask.state_dict().items())  # the decoder trained
    model.zero_grad()
    terms = model.losses(batch, model(batch))
    torch.stack([v for k, v in terms.items() if k.startswith("mask/")]).sum().backward()
    assert any(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in model.scene.parameters())  # V_fin learns
    # the same weights without the mask supervision: duocc/full, loaded strictly from everything but the decoder
    _, full = runner.build_run(runner.load_config(["duocc/full", "occplug/trainer/debug"], SMALL))
    state = {k: v for k, v in model.state_dict().items() if not k.startswith("supervision.mask.")}
    full.load_state_dict(state, strict=True)
    val = dm.dataset("val")
    frames = [dm.collate([val[i]]) for i in range(len(val))]  # one stream, frame by frame (history read)
    predictions = []
    for m in (model, full):
        m.eval()
        set_stream_stage(m, "predict")
        predictions.append([m.predict_occupancy(f) for f in frames])
        assert m.losses(frames[0], m(frames[0])).keys().isdisjoint({"mask/mask_cls"})  # no decoder at inference
    for with_mask, without in zip(*predictions, strict=True):
        assert torch.equal(with_mask, without)
    # a checkpoint rebuilds from its hyper-parameters alone (the decoder included)
    rebuilt = type(model)(**model.hparams, context=model.context)  # the run context is not a hyper-parameter
    rebuilt.load_state_dict(model.state_dict(), strict=True)


@pytest.mark.parametrize("downsample", [1, 2])
def test_the_mask_decoder_reads_v_fin_at_the_scene_s_downsample_given_once(downsample):
    """The model gives the scene's ``downsample`` (one value): the decoder's coarse grid is the scene's."""
    cfg = runner.load_config(
        ["duocc/full_mask", "occplug/trainer/debug"], [*SMALL, f"model.scene.downsample={downsample}"]
    )
    _, model = runner.build_run(cfg)
    assert model.supervision["mask"].grid == model.scene.coarse == coarse_grid(model.grid, downsample)


def test_a_config_that_still_sets_the_mask_decoder_s_downsample_is_one_error():
    with pytest.raises(ConfigError, match=r"model\.supervision\.mask\.downsample"):
        runner.load_config(
            ["duocc/full_mask", "occplug/trainer/debug"], [*SMALL, "model.supervision.mask.downsample=2"]
        )


def test_the_mask_decoder_refuses_a_scene_that_is_not_duocc_s_stream_or_not_at_its_downsample():
    """A dense scene on the run grid (``scene_downsample`` 1, as the model gives for a scene without ``downsample``)
    is one line naming ``duocc_stream``, not a silently trained decoder; a V_fin on another grid names the value."""
    source = _source(scene_downsample=1).train()
    batch = make_tiny_batch()
    volume = torch.randn(len(batch), 8, *source.label_grid.shape)
    dense = ModelOutputs(None, None, DenseVoxelScene(volume, source.label_grid), {}, lambda *a, **k: None)
    with pytest.raises(ValueError, match=r"^duocc_mask: needs V_fin of model.scene.type=duocc_stream; got Dense"):
        source(batch, dense)
    halved = _source(scene_downsample=2).train()
    with pytest.raises(ValueError, match=r"^duocc_mask: reads V_fin at scene_downsample 2 .* leave scene_downsample"):
        halved(batch, _outputs(source, batch))
