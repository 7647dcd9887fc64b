"""DQA's, V2Q's and the detector's switches to the public code's behaviour (issue #53) on small hand-made cases;
each default stays the paper's reading (the other tests hold it bit for bit)."""

import math

import pytest
import torch

from occplug.geometry import GridSpec, sample_volume
from occplug_duocc.blocks.detector import SparseDetector
from occplug_duocc.blocks.dqa import DynamicQueryAggregation
from occplug_duocc.blocks.image_aggregation import FIXED_KEY_POINTS
from occplug_duocc.blocks.v2q import VoxelToQuery

GRID = GridSpec((-4, -4, -2, 4, 4, 2), 1.0)  # (8, 8, 4)


def _dqa(**kw):
    torch.manual_seed(0)
    return DynamicQueryAggregation(16, GRID, query_channels=12, heads=2, **kw).double()


def _volume(b=1):
    return torch.randn(b, 16, *GRID.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))


def _box(x, y, z=0.0, length=2.0, w=2.0, h=2.0, yaw=0.0):
    return torch.tensor([[[x, y, z, length, w, h, yaw]]], dtype=torch.float64)


def _flat(i, j, k):
    return (i * GRID.shape[1] + j) * GRID.shape[2] + k


@pytest.mark.parametrize("path", ["sparse", "dense"])
def test_clamp_writes_a_box_wholly_outside_the_grid_into_the_face_slab(path):
    box = _box(6.5, 0.0)  # x in [5.5, 7.5]: past the +x face (x < 4) -- index range [10, 11] in x
    skip, clamp = _dqa(coverage="aabb"), _dqa(coverage="aabb", outside_boxes="clamp")
    clamp.load_state_dict(skip.state_dict())
    assert skip.edges(box[0])[0].numel() == 0
    voxel_idx, _ = clamp.edges(box[0])
    # the slab x = 7 (last index), y over the rounded range [-1, 1] + 4 -> [3, 5], z over [-1, 1] + 2 -> [1, 3]
    want = sorted(_flat(7, j, k) for j in range(3, 6) for k in range(1, 4))
    assert sorted(voxel_idx.tolist()) == want
    volume, queries, sel = _volume(), torch.randn(1, 1, 12, dtype=torch.float64), torch.ones(1, 1, dtype=torch.bool)
    out_skip = getattr(skip, path)(volume, queries, box, sel)
    out_clamp = getattr(clamp, path)(volume, queries, box, sel)
    assert torch.equal(out_skip, volume)
    changed = (out_clamp != volume).any(1).flatten(1)[0].nonzero().flatten().tolist()
    assert changed == want
    # with the exact centre test the slab lies outside the box: nothing is written either way
    centre = _dqa(outside_boxes="clamp")
    assert centre.edges(box[0])[0].numel() == 0


@pytest.mark.parametrize("path", ["sparse", "dense"])
def test_dummy_query_writes_query_0s_box_with_a_zero_feature_on_an_empty_selection(path):
    boxes = torch.cat([_box(0.5, 0.5), _box(-2.5, -2.5)], 1)  # (1, 2, 7)
    queries = torch.randn(1, 2, 12, dtype=torch.float64)
    none = torch.zeros(1, 2, dtype=torch.bool)
    volume = _volume()
    skip = _dqa()
    dummy = _dqa(empty_selection="dummy_query")
    dummy.load_state_dict(skip.state_dict())
    assert torch.equal(getattr(skip, path)(volume, queries, boxes, none), volume)
    out = getattr(dummy, path)(volume, queries, boxes, none)
    # a zero feature sums to 0: the code's mask drops its value, z = 0, so the gate multiplies nothing: V unchanged
    assert torch.equal(out, volume)
    # with the instance LayerNorm's bias moved off zero the dummy's normalised feature is that bias: it is written
    normed = _dqa(empty_selection="dummy_query", instance_norm=True)
    with torch.no_grad():
        normed.instance_norm.bias.fill_(0.1)
    out = getattr(normed, path)(volume, queries, boxes, none)
    covered = set(normed.edges(boxes[0, :1])[0].tolist())
    changed = set((out != volume).any(1).flatten(1)[0].nonzero().flatten().tolist())
    assert changed == covered and covered
    v_dummy = normed.w_v(normed.instance_norm.bias.new_full((12,), 0.1))  # LN(0) = its bias
    i = min(covered)
    x = volume.flatten(2)[0, :, i]
    gate = torch.sigmoid(normed.w_gate(torch.cat([x, v_dummy])))  # one edge: alpha = 1, z = v
    torch.testing.assert_close(out.flatten(2)[0, :, i], x + gate * v_dummy)
    # a sample that selects something is untouched by the switch
    sel = torch.tensor([[False, True]])
    torch.testing.assert_close(getattr(dummy, path)(volume, queries, boxes, sel), skip(volume, queries, boxes, sel))


def test_sin_cos_corners_equal_yaw_corners_when_normalised_and_differ_when_not():
    yaw = 0.6
    box = _box(0.3, -0.2, length=3.0, w=1.2, yaw=yaw)
    for cls_kw in ({"coverage": "aabb"}, {"coverage": "center"}):
        by_yaw = _dqa(**cls_kw)
        by_pair = _dqa(box_rotation="sin_cos", **cls_kw)
        pair = torch.cat([box[..., :6], torch.tensor([[[math.sin(yaw), math.cos(yaw)]]], dtype=torch.float64)], -1)
        assert torch.equal(by_pair.edges(pair[0])[0], by_yaw.edges(box[0])[0])
    # an unnormalised pair (norm 2) doubles the extents of the code's corners
    aabb = _dqa(coverage="aabb", box_rotation="sin_cos")
    long = torch.cat([box[..., :6], torch.tensor([[[2 * math.sin(yaw), 2 * math.cos(yaw)]]], dtype=torch.float64)], -1)
    lo, hi = aabb._index_range(long[0])
    lo1, hi1 = _dqa(coverage="aabb")._index_range(box[0])
    assert bool(((hi - lo) > (hi1 - lo1))[:, :2].all()) and torch.equal((hi - lo)[:, 2], (hi1 - lo1)[:, 2])
    # V2Q: the same points for a normalised pair, twice the offsets from the centre for the doubled one
    torch.manual_seed(0)
    v_yaw = VoxelToQuery(16, GRID, heads=2, points=3, dropout=0.0).double()
    v_pair = VoxelToQuery(16, GRID, heads=2, points=3, dropout=0.0, box_rotation="sin_cos").double()
    v_pair.load_state_dict(v_yaw.state_dict())
    q = torch.randn(1, 1, 16, dtype=torch.float64)
    pair = torch.cat([box[..., :6], torch.tensor([[[math.sin(yaw), math.cos(yaw)]]], dtype=torch.float64)], -1)
    p_yaw, p_pair = v_yaw.sample_points(q, box), v_pair.sample_points(q, pair)
    torch.testing.assert_close(p_pair, p_yaw, rtol=0, atol=1e-12)
    centre = box[0, 0, :3]
    p_long = v_pair.sample_points(q, long)
    torch.testing.assert_close((p_long - centre)[..., :2], 2 * (p_yaw - centre)[..., :2], rtol=0, atol=1e-12)
    torch.testing.assert_close(p_long[..., 2], p_yaw[..., 2], rtol=0, atol=1e-12)


def test_positional_order_permutes_the_channel_blocks():
    xyz, yxz = _dqa(), _dqa(positional_order="yxz")
    yxz.load_state_dict(xyz.state_dict())
    idx = torch.tensor([_flat(1, 5, 2), _flat(6, 0, 3)])
    a, b = xyz._positional(idx), yxz._positional(idx)
    cx = 3 * 16 // 8  # 6 + 6 + 4 channels
    assert torch.equal(b, torch.cat([a[:, cx : 2 * cx], a[:, :cx], a[:, 2 * cx :]], -1))
    assert not torch.equal(a, b)


@pytest.mark.parametrize("path", ["sparse", "dense"])
def test_output_bias_reaches_every_voxel_and_instance_norm_normalises_the_keys(path):
    plain = _dqa()
    biased = _dqa(output_bias=True)
    assert set(biased.state_dict()) - set(plain.state_dict()) == {"w_out.weight", "w_out.bias"}
    biased.load_state_dict({**biased.state_dict(), **plain.state_dict()})
    box = _box(0.5, 0.5)
    volume, queries, sel = _volume(), torch.randn(1, 1, 12, dtype=torch.float64), torch.ones(1, 1, dtype=torch.bool)
    out_plain = getattr(plain, path)(volume, queries, box, sel)
    out = getattr(biased, path)(volume, queries, box, sel)
    covered = torch.zeros(GRID.shape[0] * GRID.shape[1] * GRID.shape[2], dtype=torch.bool)
    covered[plain.edges(box[0])[0]] = True
    flat, flat_plain, v = out.flatten(2)[0], out_plain.flatten(2)[0], volume.flatten(2)[0]
    torch.testing.assert_close(flat[:, ~covered], v[:, ~covered] + biased.w_out.bias[:, None], rtol=0, atol=1e-12)
    # covered: W_O applied to the message gate * z = (plain result - V)
    msg = (flat_plain - v)[:, covered]
    torch.testing.assert_close(flat[:, covered], v[:, covered] + biased.w_out(msg.t()).t(), rtol=0, atol=1e-12)
    # instance_norm: the keys / values read LN(q), so a query and its shifted copy write the same
    normed = _dqa(instance_norm=True)
    one = getattr(normed, path)(volume, queries, box, sel)
    two = getattr(normed, path)(volume, queries + 1.0, box, sel)
    torch.testing.assert_close(one, two, rtol=0, atol=1e-9)
    assert not torch.allclose(out_plain, getattr(plain, path)(volume, queries + 1.0, box, sel))


def test_dqa_switches_are_validated():
    with pytest.raises(ValueError, match="outside_boxes must be 'skip' or 'clamp', got 'clip'"):
        DynamicQueryAggregation(16, GRID, heads=2, outside_boxes="clip")
    with pytest.raises(ValueError, match="positional_order"):
        DynamicQueryAggregation(16, GRID, heads=2, positional_order="zyx")
    with pytest.raises(ValueError, match="box_rotation"):
        VoxelToQuery(16, GRID, heads=2, box_rotation="quaternion")
    with pytest.raises(ValueError, match="fixed_key_points needs more than 7 points"):
        VoxelToQuery(16, GRID, heads=2, points=3, fixed_key_points=True)
    with pytest.raises(ValueError, match="v2q_placement"):
        SparseDetector(num_classes=2, v2q_placement="inside")


def _recorder(mod, seen, name):
    """``mod.sample_points`` that records the queries it was given under ``seen[name]``."""
    real = type(mod).sample_points

    def record(x, boxes):
        seen[name] = x
        return real(mod, x, boxes)

    return record


def _v2q(**kw):
    torch.manual_seed(0)
    return VoxelToQuery(16, GRID, heads=4, points=3, dropout=0.0, **kw).double()


def test_v2q_offset_input_fixed_key_points_and_value_bias():
    q = torch.randn(1, 2, 16, dtype=torch.float64)
    pos = torch.randn(1, 2, 16, dtype=torch.float64)
    boxes = torch.tensor([[[0.5, -0.5, 0.0, 3.0, 1.5, 1.0, 0.6], [3.5, 3.5, 1.5, 2.0, 2.0, 2.0, 0.0]]])
    boxes = boxes.double()
    volume = _volume()
    both, feature = _v2q(), _v2q(offset_input="feature")
    feature.load_state_dict(both.state_dict())
    with torch.no_grad():
        both.offsets.weight.normal_()
        feature.offsets.weight.copy_(both.offsets.weight)
    # offsets from the feature alone: the query_pos moves the points of the default only (the weights read it in both)
    seen = {}
    for name, mod in (("both", both), ("feature", feature)):
        mod.sample_points = _recorder(mod, seen, name)
    both(volume, q, boxes, pos), feature(volume, q, boxes, pos)
    assert torch.equal(seen["both"], q + pos) and torch.equal(seen["feature"], q)
    del both.sample_points, feature.sample_points
    # fixed key points: the first 7 of the flat H * O points are the code's, whatever the query
    fixed = _v2q(fixed_key_points=True)
    assert fixed.offsets.out_features == (4 * 3 - 7) * 3
    pts = fixed.sample_points(q, boxes[..., :7] * torch.tensor([1, 1, 1, 1, 1, 1, 0.0], dtype=torch.float64))
    frac = torch.tensor(FIXED_KEY_POINTS, dtype=torch.float64) * boxes[0, :, None, 3:6]  # yaw 0: axis aligned
    torch.testing.assert_close(pts.view(1, 2, 12, 3)[0, :, :7], boxes[0, :, None, :3] + frac, rtol=0, atol=1e-12)
    # value bias: applied before sampling, so the bias comes scaled by the in-grid mass (1 inside, less at a face)
    biased = _v2q(value_bias=True)
    plain = _v2q()
    biased.load_state_dict({**biased.state_dict(), **plain.state_dict()})
    with torch.no_grad():
        biased.value_bias.normal_()
        biased.out_proj.weight.copy_(torch.eye(16))
        plain.out_proj.weight.copy_(torch.eye(16))
    gain = biased(volume, q, boxes, pos) - plain(volume, q, boxes, pos)  # (1, 2, 16): sum_o alpha * mass * bias
    pts = plain.sample_points(q + pos, boxes).view(1, -1, 3)
    mass = sample_volume(torch.ones_like(volume[:, :1]), GRID, pts).view(1, 2, 4, 3)
    alpha = plain.attn(q + pos).view(1, 2, 4, 3).softmax(-1)
    want = ((alpha * mass).sum(-1)[..., None] * biased.value_bias.view(4, 4)).reshape(1, 2, 16)
    torch.testing.assert_close(gain, want, rtol=0, atol=1e-12)
    assert bool((mass[0, 0] == 1).all()) and bool((mass[0, 1] < 1).any())  # the second box reaches a face


def _detector(**kw):
    return SparseDetector(
        num_classes=3,
        channels=32,
        level_channels=(16,),
        num_queries=12,
        num_layers=2,
        num_temporal=4,
        anchor_range=(2.0, -6.0, -1.0, 20.0, 6.0, 2.0),
        dropout=0.0,
        **kw,
    )


def test_v2q_placement_runs_v2q_inside_the_last_layer_before_its_refinement():
    # one forward-looking camera 1.5 m up (OpenCV axes: x right = -y ego, y down = -z ego, z forward = +x ego)
    k = torch.tensor([[20.0, 0.0, 23.5], [0.0, 20.0, 15.5], [0.0, 0.0, 1.0]]).expand(1, 1, 3, 3)
    c2e = torch.eye(4)
    c2e[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    c2e[:3, 3] = torch.tensor([0.5, 0.0, 1.5])
    c2e, aug = c2e.expand(1, 1, 4, 4), torch.eye(3).expand(1, 1, 3, 3)
    levels = [torch.randn(1, 1, 16, 8, 12, generator=torch.Generator().manual_seed(0))]
    torch.manual_seed(0)
    after = _detector()
    before = _detector(v2q_placement="before_last_refinement")
    before.load_state_dict(after.state_dict())
    after.eval(), before.eval()
    with torch.no_grad():  # a last refinement that reads its features (its last Linear starts at zero)
        w = after.layers[-1].refine[-1].weight
        w.copy_(torch.linspace(-0.1, 0.1, w.numel()).view_as(w))
        before.layers[-1].refine[-1].weight.copy_(w)
    seen = []

    def v2q(x, anchors, embed):
        seen.append(anchors.clone())
        return x + 1.0

    a = after(levels, (32, 48), k, c2e, aug, v2q=v2q)
    assert seen == []  # after_last_refinement: QueryAgg calls V2Q itself, the detector ignores the hook
    b = before(levels, (32, 48), k, c2e, aug, v2q=v2q)
    assert len(seen) == 1 and torch.equal(seen[0], a.encoded_boxes[-2])  # the last layer's input anchors
    assert torch.equal(b.encoded_boxes[0], a.encoded_boxes[0])
    assert torch.allclose(b.features, a.features + 1.0)  # the hook's output is the layer's output feature
    assert not torch.allclose(b.encoded_boxes[-1], a.encoded_boxes[-1])  # ... and the last refinement read it
    assert not torch.allclose(b.cls_logits[-1], a.cls_logits[-1])


def test_code_recipe_sets_every_switch_and_trains():
    """``duocc/code_recipe`` builds DQA, V2Q and the detector with the public code's switches; a step of it trains
    (V2Q inside the detector's last layer: its value bias and the detector's last refinement get gradients)."""
    from occplug.run import runner

    small = ["grid.range=[-8.0,-8.0,-1.0,8.0,8.0,5.4]", "model.encoder.out_channels=16", "model.encoder.width=16"]
    cfg = runner.load_config(["duocc/code_recipe", "occplug/trainer/debug"], small)
    torch.manual_seed(0)
    dm, model = runner.build_run(cfg)
    qa = model.scene.query_agg
    dqa, v2q = qa.dqa, qa.v2q
    assert dqa.w_out is not None and dqa.instance_norm is not None
    assert (dqa.outside_boxes, dqa.empty_selection, dqa.box_rotation, dqa.positional_order) == (
        "clamp",
        "dummy_query",
        "sin_cos",
        "yxz",
    )
    assert (v2q.offset_input, v2q.value_bias is not None, v2q.fixed, v2q.box_rotation) == (
        "feature",
        True,
        7,
        "sin_cos",
    )
    assert qa.detector.v2q_placement == "before_last_refinement"
    data = dm.dataset("train")
    batch = dm.collate([data[0], data[3]])
    losses = model.losses(batch, model(batch))
    loss = torch.stack(list(losses.values())).sum()
    assert torch.isfinite(loss)
    # V2Q runs before the detector's last classification: the detection loss itself reaches V2Q's parameters
    (g,) = torch.autograd.grad(losses["detection/det_cls"], v2q.value_bias, retain_graph=True)
    assert g.abs().sum() > 0
    loss.backward()
    # nothing is selected at the start (the dummy query sends no value), yet W_O's bias reaches every voxel
    assert v2q.value_bias.grad.abs().sum() > 0 and dqa.w_out.bias.grad.abs().sum() > 0
    model.eval()
    assert model.predict_occupancy(batch).shape == (2, 20, 20, 8)
