"""DuOcc's image-to-query detector, its loss, V2Q and the detection mAP against their definitions (§3.2, suppl. A.4)."""

import math

import pytest
import torch

from occplug.geometry import GridSpec, make_pose, project_to_image, rotation_z, sample_volume, unproject_from_image
from occplug_duocc.blocks.boxes import decode_boxes
from occplug_duocc.blocks.detection_loss import detection_loss
from occplug_duocc.blocks.detector import (
    DetectorOutput,
    DetectorState,
    SparseDetector,
    propagate_state,
    select_detections,
)
from occplug_duocc.blocks.image_aggregation import sample_image_features
from occplug_duocc.blocks.matching import encode_boxes
from occplug_duocc.blocks.v2q import VoxelToQuery
from occplug_duocc.tools.detection_eval import detection_map

H, W = 32, 48
# one forward-looking camera (OpenCV axes: x right = -y ego, y down = -z ego, z forward = +x ego), 1.5 m up
CAM_R = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _cameras(b=1, n=1, aug=False):
    k = torch.tensor([[40.0, 0.0, 47.5], [0.0, 40.0, 31.5], [0.0, 0.0, 1.0]])  # calibrated on a 96 x 64 image
    c2e = make_pose(CAM_R, torch.tensor([0.5, 0.0, 1.5]))
    # the network sees it halved and cropped by one pixel at the top (or, without aug, the original's top-left)
    a = torch.tensor([[0.5, 0.0, 0.0], [0.0, 0.5, -1.0], [0.0, 0.0, 1.0]]) if aug else torch.eye(3)
    if not aug:
        k = torch.tensor([[20.0, 0.0, 23.5], [0.0, 20.0, 15.5], [0.0, 0.0, 1.0]])
    return k.expand(b, n, 3, 3).clone(), c2e.expand(b, n, 4, 4).clone(), a.expand(b, n, 3, 3).clone()


def _pose(yaw=0.0, t=(0.0, 0.0, 0.0), b=1):
    pose = make_pose(rotation_z(torch.tensor(yaw, dtype=torch.float64)), torch.tensor(t, dtype=torch.float64))
    return pose.expand(b, 4, 4).clone()


def _detector(**kw):
    kw = {
        "num_classes": 3,
        "channels": 32,
        "level_channels": (16, 32),
        "num_queries": 12,
        "num_layers": 2,
        "num_temporal": 4,
        "heads": 4,
        "groups": 4,
        "anchor_range": (2.0, -6.0, -1.0, 20.0, 6.0, 2.0),
        "dropout": 0.0,
        **kw,
    }
    return SparseDetector(**kw)


def _levels(b=1, n=1, seed=0):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(b, n, 16, H // 4, W // 4, generator=g), torch.randn(b, n, 32, H // 8, W // 8, generator=g)]


# ---------------------------------------------------------------------------------------------- detector


def test_detector_output_shapes_and_state_over_two_frames():
    torch.manual_seed(0)
    det = _detector()
    k, c2e, a = _cameras(b=2, n=2)
    out = det(_levels(2, 2), (H, W), k, c2e, a, ego_to_global=_pose(b=2), timestamp=torch.zeros(2, dtype=torch.float64))
    assert len(out.cls_logits) == len(out.encoded_boxes) == 2
    assert all(t.shape == (2, 12, 3) for t in out.cls_logits)
    assert all(t.shape == (2, 12, 9) for t in out.boxes)
    assert out.features.shape == out.anchor_embed.shape == (2, 12, 32)
    assert out.state.anchors.shape == (2, 4, 10) and out.state.features.shape == (2, 4, 32)
    assert not out.state.features.requires_grad
    nxt = det(
        _levels(2, 2, seed=1),
        (H, W),
        k,
        c2e,
        a,
        state=out.state,
        ego_to_global=_pose(t=(1.0, 0.0, 0.0), b=2),
        timestamp=torch.full((2,), 0.5, dtype=torch.float64),
        reset=torch.tensor([False, True]),
    )
    assert nxt.cls_logits[-1].shape == (2, 12, 3) and torch.isfinite(nxt.boxes[-1]).all()
    # decoded boxes are Frame boxes: encoding them again gives the regressed encoding (unit sin/cos aside)
    enc = nxt.encoded_boxes[-1]
    unit = enc[..., 6:8] / enc[..., 6:8].norm(dim=-1, keepdim=True)
    torch.testing.assert_close(encode_boxes(nxt.boxes[-1]), torch.cat([enc[..., :6], unit, enc[..., 8:]], -1))


def test_checkpointed_aggregation_gives_the_values_and_gradients_of_the_plain_one():
    torch.manual_seed(0)
    plain, chunked = _detector(), _detector(checkpoint_aggregation=True)
    chunked.load_state_dict(plain.state_dict())
    k, c2e, a = _cameras(b=2, n=2)
    results = []
    for det in (plain, chunked):
        levels = [t.requires_grad_() for t in _levels(2, 2)]
        out = det(levels, (H, W), k, c2e, a, ego_to_global=_pose(b=2), timestamp=torch.zeros(2, dtype=torch.float64))
        loss = sum(t.square().sum() for t in out.cls_logits) + out.features.sin().sum() + out.boxes[-1].sum()
        loss.backward()
        results.append((out.cls_logits[-1], out.features, [t.grad for t in levels], [p.grad for p in det.parameters()]))
    (cls0, f0, lg0, pg0), (cls1, f1, lg1, pg1) = results
    torch.testing.assert_close(cls0, cls1)
    torch.testing.assert_close(f0, f1)
    for g0, g1 in zip([*lg0, *pg0], [*lg1, *pg1], strict=True):
        assert (g0 is None) == (g1 is None)
        if g0 is not None:
            torch.testing.assert_close(g0, g1, rtol=1e-4, atol=1e-6)
    assert any(g is not None and g.abs().sum() > 0 for g in lg1)  # the image levels get gradients through it


def test_a_state_reset_everywhere_gives_the_stateless_output_on_the_masked_path(monkeypatch):
    """Eager skips an all-invalid state; an exported graph cannot branch and runs the masked path: the same result."""
    torch.manual_seed(0)
    det = _detector().eval()
    k, c2e, a = _cameras(b=2)
    t0 = torch.zeros(2, dtype=torch.float64)
    with torch.no_grad():
        state = det(_levels(2), (H, W), k, c2e, a, ego_to_global=_pose(b=2), timestamp=t0).state
        levels, pose, t1 = _levels(2, seed=1), _pose(t=(1.0, 0.0, 0.0), b=2), torch.full((2,), 0.5, dtype=torch.float64)
        fresh = det(levels, (H, W), k, c2e, a, ego_to_global=pose, timestamp=t1)
        reset = torch.tensor([True, True])
        skipped = det(levels, (H, W), k, c2e, a, state=state, ego_to_global=pose, timestamp=t1, reset=reset)
        monkeypatch.setattr(torch.compiler, "is_compiling", lambda: True)
        masked = det(levels, (H, W), k, c2e, a, state=state, ego_to_global=pose, timestamp=t1, reset=reset)
        kept = det(levels, (H, W), k, c2e, a, state=state, ego_to_global=pose, timestamp=t1)
    for out in (skipped, masked):
        for got, want in zip((*out.cls_logits, *out.boxes), (*fresh.cls_logits, *fresh.boxes), strict=True):
            torch.testing.assert_close(got, want, rtol=0, atol=1e-6)
        for field in ("anchors", "features", "confidence"):
            torch.testing.assert_close(getattr(out.state, field), getattr(fresh.state, field), rtol=0, atol=1e-6)
    assert float((kept.cls_logits[-1] - fresh.cls_logits[-1]).abs().max()) > 1e-4  # a valid state does matter


def test_key_point_of_an_anchor_projects_onto_the_pixel_of_project_to_image_and_reads_it():
    k, c2e, a = _cameras(aug=True)
    u, v, depth = 17.0, 9.0, 7.25  # an augmented-image pixel centre and its depth
    point = unproject_from_image(torch.tensor([[[[u, v]]]]), torch.tensor([[[depth]]]), k, c2e, a)[0, 0, 0]
    uv_core, _ = project_to_image(point.view(1, 1, 1, 3), k, c2e, a)
    torch.testing.assert_close(uv_core[0, 0, 0], torch.tensor([u, v]), atol=1e-4, rtol=0)

    det = _detector()
    anchors = det.anchors.detach().clone()[None]
    anchors[0, 5, :3] = point  # anchor 5 sits at the ego point; its yaw and size do not move its centre
    anchors[0, 5, 6:8] = torch.tensor([math.sin(0.7), math.cos(0.7)])
    deform = det.layers[0].deformable
    points = deform.key_points(anchors, torch.randn(1, 12, 32))
    assert points.shape == (1, 12, 7 + 6, 3)
    assert torch.equal(points[0, 5, 0], point)  # key point 0 is the centre

    # ramps u + 1000 v (stride 1) and the same ramp in level-2 cell units (stride 2): bilinear reads them exactly
    cols, rows = torch.meshgrid(
        torch.arange(W, dtype=torch.float32), torch.arange(H, dtype=torch.float32), indexing="xy"
    )
    fine = (cols + 1000 * rows).view(1, 1, 1, H, W)
    c2, r2 = torch.meshgrid(
        torch.arange(W // 2, dtype=torch.float32), torch.arange(H // 2, dtype=torch.float32), indexing="xy"
    )
    coarse = (c2 + 1000 * r2).view(1, 1, 1, H // 2, W // 2)
    feats, uv, valid = sample_image_features([fine, coarse], points, (H, W), k, c2e, a)
    torch.testing.assert_close(uv[0, 0, 5, 0], uv_core[0, 0, 0], atol=0, rtol=0)
    assert valid[0, 0, 5, 0]
    torch.testing.assert_close(feats[0][0, 5, 0, 0, 0], torch.tensor(u + 1000 * v), atol=2e-3, rtol=0)
    # a stride-2 cell j is centred on pixel 2j + 0.5: pixel u reads cell (u + 0.5) / 2 - 0.5
    expect = (u + 0.5) / 2 - 0.5 + 1000 * ((v + 0.5) / 2 - 0.5)
    torch.testing.assert_close(feats[1][0, 5, 0, 0, 0], torch.tensor(expect), atol=2e-3, rtol=0)


def test_point_behind_the_camera_reads_zeros():
    k, c2e, a = _cameras()
    behind = torch.tensor([-5.0, 0.0, 1.5]).view(1, 1, 1, 3)  # 5.5 m behind a forward camera, on its axis
    feats, _, valid = sample_image_features([torch.ones(1, 1, 2, H, W)], behind, (H, W), k, c2e, a)
    assert not valid.any() and torch.equal(feats[0], torch.zeros_like(feats[0]))


def _state(b=2, k=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    anchors = torch.randn(b, k, 10, generator=g)
    yaw = torch.rand(b, k, generator=g) * 6 - 3
    anchors[..., 6], anchors[..., 7] = yaw.sin(), yaw.cos()
    return DetectorState(anchors, torch.randn(b, k, 8, generator=g), torch.rand(b, k, generator=g))


def test_identity_motion_keeps_the_propagated_anchors_unchanged():
    state = _state()
    state.ego_to_global, state.timestamp = _pose(0.3, (5.0, -2.0, 0.1), b=2), torch.zeros(2, dtype=torch.float64)
    moved, valid = propagate_state(state, state.ego_to_global.clone(), torch.full((2,), 0.5, dtype=torch.float64))
    assert valid.all()
    torch.testing.assert_close(moved.anchors, state.anchors, atol=1e-6, rtol=0)
    assert torch.equal(moved.features, state.features) and torch.equal(moved.confidence, state.confidence)
    # without poses at all the frames share the ego frame: bit for bit
    bare = DetectorState(state.anchors, state.features, state.confidence)
    assert torch.equal(propagate_state(bare)[0].anchors, state.anchors)


def test_pure_translation_moves_the_centres_by_it_and_nothing_else():
    state = _state()
    state.ego_to_global = _pose(b=2)
    # the ego drives 1.5 m forward and 2 m to the right: a static box is 1.5 m closer and 2 m further left
    moved, _ = propagate_state(state, _pose(t=(1.5, -2.0, 0.0), b=2))
    torch.testing.assert_close(moved.anchors[..., :3], state.anchors[..., :3] - torch.tensor([1.5, -2.0, 0.0]))
    assert torch.equal(moved.anchors[..., 3:], state.anchors[..., 3:])
    # a turn of the ego by +0.4 rad turns every box by -0.4 rad in the new frame, velocity with it
    moved, _ = propagate_state(state, _pose(yaw=0.4, b=2))
    yaw_before = torch.atan2(state.anchors[..., 6], state.anchors[..., 7])
    yaw_after = torch.atan2(moved.anchors[..., 6], moved.anchors[..., 7])
    torch.testing.assert_close(
        torch.remainder(yaw_after - yaw_before + 0.4 + math.pi, 2 * math.pi) - math.pi,
        torch.zeros(2, 3),
        atol=1e-5,
        rtol=0,
    )
    torch.testing.assert_close(moved.anchors[..., 8:].norm(dim=-1), state.anchors[..., 8:].norm(dim=-1))


def test_constant_velocity_and_time_limit():
    state = _state()
    state.ego_to_global, state.timestamp = _pose(b=2), torch.zeros(2, dtype=torch.float64)
    now = torch.tensor([0.5, 3.0], dtype=torch.float64)
    moved, valid = propagate_state(state, _pose(b=2), now, use_velocity=True, max_time_interval=2.0)
    assert valid.tolist() == [True, False]
    step = torch.cat([state.anchors[..., 8:10], torch.zeros(2, 3, 1)], -1) * now.float()[:, None, None]
    torch.testing.assert_close(moved.anchors[..., :3], state.anchors[..., :3] + step)


def test_detector_prepends_the_propagated_instances():
    torch.manual_seed(0)
    det = _detector(num_layers=1)  # one layer: the cache is prepended before it, so its anchors are refined once
    k, c2e, a = _cameras()
    first = det(_levels(), (H, W), k, c2e, a)
    # a second frame with the same images and no motion: the cached instances enter as the first k queries
    refine = det.layers[0].refine[-1]
    with torch.no_grad():
        refine.bias.zero_()
        refine.weight.zero_()  # no refinement: the output boxes are the input anchors
    second = det(_levels(), (H, W), k, c2e, a, state=first.state)
    assert torch.equal(second.encoded_boxes[0][:, :4], first.state.anchors)
    reset = det(_levels(), (H, W), k, c2e, a, state=first.state, reset=torch.tensor([True]))
    assert torch.equal(reset.encoded_boxes[0], det.anchors.detach()[None])


# ---------------------------------------------------------------------------------------------- loss


GT_BOX = torch.tensor([[8.0, 1.0, 0.5, 4.0, 1.8, 1.6, 0.3, 1.0, 0.0]])


def _output_with(boxes9, label, q=6, k=3, confident=10.0):
    logits = torch.full((1, q, k), -confident)
    logits[0, 2, label] = confident
    enc = encode_boxes(torch.tensor([[10.0, -5.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0]]).expand(1, q, 9)).clone()
    enc[0, 2] = encode_boxes(boxes9)[0]
    return DetectorOutput([logits], [enc])


def test_loss_of_a_perfect_prediction_is_lower_than_of_a_shifted_one_and_finite_without_ground_truth():
    perfect = detection_loss(_output_with(GT_BOX, 1), [torch.tensor([1])], [GT_BOX])
    shifted_box = GT_BOX.clone()
    shifted_box[0, :2] += torch.tensor([1.0, -0.5])
    shifted = detection_loss(_output_with(shifted_box, 1), [torch.tensor([1])], [GT_BOX])
    wrong_class = detection_loss(_output_with(GT_BOX, 2), [torch.tensor([1])], [GT_BOX])
    assert perfect["det_box"] == 0
    assert perfect["det_cls"] < 1e-6
    torch.testing.assert_close(shifted["det_box"], torch.tensor(0.25 * (2 * 1.0 + 2 * 0.5)))  # weights 2 on x, y
    assert sum(perfect.values()) < sum(shifted.values()) and sum(perfect.values()) < sum(wrong_class.values())
    # no ground truth: everything is background; the loss is finite and has gradients
    out = _output_with(GT_BOX, 1)
    out.cls_logits[0].requires_grad_(True)
    empty = detection_loss(out, [torch.zeros(0, dtype=torch.long)], [torch.zeros(0, 9)])
    assert torch.isfinite(empty["det_cls"]) and empty["det_cls"] > 0 and empty["det_box"] == 0
    empty["det_cls"].backward()
    assert torch.isfinite(out.cls_logits[0].grad).all()


def test_loss_mixes_samples_with_and_without_ground_truth_and_ignores_nan_velocity():
    torch.manual_seed(0)
    det = _detector()
    k, c2e, a = _cameras(b=2)
    out = det(_levels(2), (H, W), k, c2e, a)
    gt = GT_BOX.clone()
    gt[0, 7:] = float("nan")  # unknown velocity
    loss = detection_loss(
        out, [torch.tensor([0]), torch.zeros(0, dtype=torch.long)], [gt, torch.zeros(0, 9)], reg_score_threshold=None
    )
    assert all(torch.isfinite(v) for v in loss.values()) and loss["det_box"] > 0
    sum(loss.values()).backward()
    assert all(torch.isfinite(p.grad).all() for p in det.parameters() if p.grad is not None)


def test_loss_falls_when_fitting_one_box_on_fixed_image_features():
    torch.manual_seed(0)
    det = _detector()
    k, c2e, a = _cameras()
    levels = _levels(seed=3)
    opt = torch.optim.Adam(det.parameters(), lr=3e-3)
    losses = []
    for _ in range(30):
        out = det(levels, (H, W), k, c2e, a)
        loss = sum(detection_loss(out, [torch.tensor([1])], [GT_BOX]).values())
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.5 * losses[0], losses
    best = select_detections(out, top_k=1)[0]
    assert best[2].item() == 1  # the top (query, class) pair is the right class


# ---------------------------------------------------------------------------------------------- V2Q


GRID = GridSpec((-4, -4, -2, 4, 4, 2), 1.0)  # (8, 8, 4), 1 m voxels


def test_v2q_with_zero_offsets_reads_the_voxel_under_the_box_centre():
    torch.manual_seed(0)
    v2q = VoxelToQuery(16, GRID, heads=4, points=3, dropout=0.0)
    with torch.no_grad():
        v2q.offsets.weight.zero_()
        v2q.offsets.bias.zero_()  # every point at the box centre
    volume = torch.randn(2, 16, *GRID.shape)
    queries = torch.randn(2, 5, 16)
    idx = torch.tensor([[2, 5, 1], [7, 0, 3], [3, 3, 2], [0, 7, 0], [4, 1, 1]])
    centres = GRID.index_to_coord(idx)
    boxes = torch.cat([centres, torch.tensor([3.0, 1.5, 1.2]).expand(5, 3), torch.rand(5, 1) * 6 - 3], -1).expand(
        2, 5, 7
    )
    out = v2q(volume, queries, boxes)
    voxel = volume[:, :, idx[:, 0], idx[:, 1], idx[:, 2]].transpose(1, 2)  # (2, 5, 16)
    torch.testing.assert_close(sample_volume(volume, GRID, centres.expand(2, 5, 3)), voxel, atol=1e-6, rtol=0)
    # the attention weights sum to 1 per head, so the output is W [W'_h V(centre)]_h whatever they are
    heads = v2q.value_proj(voxel)
    torch.testing.assert_close(out, queries + v2q.out_proj(heads), atol=1e-5, rtol=0)
    with torch.no_grad():  # identity projections: the query gains exactly the voxel's feature
        v2q.value_proj.weight.copy_(torch.eye(16))
        v2q.out_proj.weight.copy_(torch.eye(16))
        v2q.out_proj.bias.zero_()
    torch.testing.assert_close(v2q(volume, queries, boxes), queries + voxel, atol=1e-5, rtol=0)


def test_v2q_points_stay_inside_the_box_and_gradients_reach_offsets():
    torch.manual_seed(0)
    v2q = VoxelToQuery(16, GRID, volume_channels=8, heads=4, points=3, dropout=0.0)
    boxes = torch.tensor([[[0.5, -0.5, 0.0, 3.0, 1.5, 1.0, 0.6]]])
    pts = v2q.sample_points(torch.randn(1, 1, 16), boxes)
    assert pts.shape == (1, 1, 4, 3, 3)
    from occplug_duocc.blocks.dqa import points_in_boxes

    assert points_in_boxes(pts.view(1, -1, 3), boxes).all()
    out = v2q(torch.randn(1, 8, *GRID.shape), torch.randn(1, 1, 16), boxes)
    out.sum().backward()
    assert v2q.offsets.weight.grad.abs().sum() > 0


# ---------------------------------------------------------------------------------------------- mAP


def _boxes(xy):
    xy = torch.tensor(xy, dtype=torch.float32).view(-1, 2)
    return torch.cat([xy, torch.zeros(len(xy), 1), torch.ones(len(xy), 3), torch.zeros(len(xy), 1)], -1)


def test_map_is_one_for_perfect_and_zero_for_far_predictions():
    gt_boxes = [_boxes([[1, 2], [5, 5], [-3, 0]]), _boxes([[10, 0]])]
    gt_labels = [torch.tensor([0, 1, 0]), torch.tensor([2])]
    scores = [torch.tensor([0.9, 0.8, 0.7]), torch.tensor([0.6])]
    res = detection_map(gt_boxes, scores, gt_labels, gt_boxes, gt_labels)
    assert res["mAP"] == pytest.approx(1.0) and set(res["AP"]) == {0, 1, 2}
    far = [b + torch.tensor([20.0, 0, 0, 0, 0, 0, 0]) for b in gt_boxes]
    assert detection_map(far, scores, gt_labels, gt_boxes, gt_labels)["mAP"] == 0.0
    wrong = [torch.tensor([1, 2, 1]), torch.tensor([0])]  # right places, wrong classes
    assert detection_map(gt_boxes, scores, wrong, gt_boxes, gt_labels)["mAP"] == 0.0


def test_map_of_a_hand_made_case():
    # two ground truths; predictions by score: a false positive, then a hit on each ground truth (1.5 m, 0.3 m off)
    gt = [_boxes([[0, 0], [10, 0]])]
    labels = [torch.tensor([0, 0])]
    preds = _boxes([[30, 30], [10, 1.5], [0.3, 0]])
    scores = [torch.tensor([0.9, 0.8, 0.7])]
    plabels = [torch.tensor([0, 0, 0])]
    # precision at each prediction 0, 1/2, 2/3 at recall 0, 1/2, 1: interpolated p(r) = r up to r = 1/2,
    # then 1/2 + (r - 1/2) / 3. nuScenes keeps recalls 0.11 .. 1.00 and max(p - 0.1, 0) / 0.9:
    low = sum(i / 100 - 0.1 for i in range(11, 51))
    high = sum(0.5 + (i - 50) / 300 - 0.1 for i in range(51, 101))
    expect = (low + high) / 90 / 0.9  # = 0.4006...
    res = detection_map([preds], scores, plabels, gt, labels, thresholds=(2.0,))
    assert res["mAP"] == pytest.approx(expect, abs=1e-9)
    # no clipping: the devkit still drops the recall-0 bin, so the mean runs over recalls 0.01 .. 1.00
    plain = (sum(i / 100 for i in range(1, 51)) + sum(0.5 + (i - 50) / 300 for i in range(51, 101))) / 100
    res = detection_map([preds], scores, plabels, gt, labels, thresholds=(2.0,), min_recall=0, min_precision=0)
    assert res["mAP"] == pytest.approx(plain, abs=1e-9)
    # at 1 m the 1.5 m hit is a miss: precision 0, 0, 1/3 at recall 0, 0, 1/2 -> p(r) = 2r/3 up to 1/2, then 0
    res = detection_map([preds], scores, plabels, gt, labels, thresholds=(1.0, 2.0))
    at_one = sum(max(2 * i / 300 - 0.1, 0) for i in range(11, 51)) / 90 / 0.9
    assert res["AP@"][1.0] == pytest.approx(at_one, abs=1e-9)
    assert res["mAP"] == pytest.approx((at_one + expect) / 2, abs=1e-9)


def test_decode_inverts_encode():
    boxes = torch.tensor([[1.0, -2.0, 0.5, 4.0, 1.8, 1.6, -2.5, 0.3, -0.1]])
    torch.testing.assert_close(decode_boxes(encode_boxes(boxes)), boxes)


def test_detector_loss_and_map_on_the_core_batch():
    from occplug.testing import make_tiny_batch

    batch = make_tiny_batch()  # 2 samples, 6 cameras, boxes (M, 9) with Occ3D class ids
    torch.manual_seed(0)
    b, n, _, h, w = batch.images.shape
    levels = [torch.randn(b, n, 16, h // 4, w // 4), torch.randn(b, n, 32, h // 8, w // 8)]
    det = _detector(num_classes=18)
    first = det.forward_batch(levels, batch)
    assert torch.equal(first.state.ego_to_global, batch.ego_to_global)
    out = det.forward_batch(levels, batch, first.state)  # same poses: identity motion, dt = 0
    loss = detection_loss(out, batch.box_labels, batch.boxes)
    assert all(torch.isfinite(v) for v in loss.values())
    found = select_detections(out, top_k=20)
    res = detection_map(
        [f[0] for f in found], [f[1] for f in found], [f[2] for f in found], batch.boxes, batch.box_labels
    )
    assert 0.0 <= res["mAP"] <= 1.0 and set(res["AP"]) == set(torch.cat(batch.box_labels).tolist())
    truth = detection_map(
        batch.boxes, [torch.ones(len(x)) for x in batch.boxes], batch.box_labels, batch.boxes, batch.box_labels
    )
    assert truth["mAP"] == pytest.approx(1.0)
