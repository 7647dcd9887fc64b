"""DuOcc's building blocks against their definitions (paper §3.1 Eqs. 1-5, §3.2 Eqs. 7-10, suppl. A.2, A.4)."""

import math

import pytest
import torch
import torch.nn.functional as F

from occplug.geometry import GridSpec, make_pose, rotation_z, warp_volume
from occplug_duocc.blocks.dqa import (
    CODE_SELECTION,
    PAPER_SELECTION,
    DynamicQueryAggregation,
    VoxelFFN,
    box_iou_3d,
    points_in_boxes,
    select_queries,
)
from occplug_duocc.blocks.matching import encode_boxes, hungarian_match, matching_cost
from occplug_duocc.blocks.stream_agg import RefineNet, StreamAggregation, forecast_loss, occupied_loss

# power-of-two extents and 1 m voxels: voxel centres normalise to exact binary fractions, so an identity
# or whole-voxel warp samples exactly one voxel with weight 1 (bit-exact comparisons are meaningful)
GRID = GridSpec((-4, -4, -2, 4, 4, 2), 1.0)  # (8, 8, 4)


def _pose(yaw: float = 0.0, t=(0.0, 0.0, 0.0), batch: int = 1) -> torch.Tensor:
    pose = make_pose(rotation_z(torch.tensor(yaw, dtype=torch.float64)), torch.tensor(t, dtype=torch.float64))
    return pose.expand(batch, 4, 4).clone()


def _volume(b=2, c=8, seed=0) -> torch.Tensor:
    return torch.randn(b, c, *GRID.shape, generator=torch.Generator().manual_seed(seed))


def _bare(**kw) -> StreamAggregation:
    kw = {"refine": False, "occupied_head": False, "forecast_head": False, **kw}
    return StreamAggregation(8, 5, GRID, **kw)


# ---------------------------------------------------------------------------------------------- StreamAgg


def test_identity_motion_without_refinenet_adds_history_and_current_exactly():
    v_curr, v_hist = _volume(seed=1), _volume(seed=2)
    out = _bare()(v_curr, v_hist, _pose(batch=2), torch.zeros(2, dtype=torch.bool))
    assert torch.equal(out.warped, v_hist)
    assert torch.equal(out.fused, v_hist + v_curr)  # Eq. 5 with V_refwarp = V_warp


def test_translation_by_one_voxel_shifts_the_warped_history_by_one_voxel():
    v_hist = _volume(seed=3)
    agg = _bare()
    # a static point at x in the previous ego frame sits at x + 1 m in the current one
    out = agg(torch.zeros_like(v_hist), v_hist, _pose(t=(1.0, 0.0, 0.0), batch=2))
    assert torch.equal(out.warped[:, :, 1:], v_hist[:, :, :-1])
    assert torch.equal(out.warped[:, :, 0], torch.zeros_like(out.warped[:, :, 0]))  # not seen before: zeros
    out = agg(torch.zeros_like(v_hist), v_hist, _pose(t=(0.0, -1.0, 0.0), batch=2))
    assert torch.equal(out.warped[:, :, :, :-1], v_hist[:, :, :, 1:])
    # and on a grid whose voxel size is no power of two, to round-off
    grid = GridSpec((-3.2, -3.2, -1.6, 3.2, 3.2, 1.6), 0.8)
    agg = StreamAggregation(8, 5, grid, refine=False, occupied_head=False, forecast_head=False)
    out = agg(torch.zeros_like(v_hist), v_hist, _pose(t=(0.8, 0.0, 0.0), batch=2))
    assert torch.allclose(out.warped[:, :, 1:], v_hist[:, :, :-1], atol=1e-5)


def test_rotation_there_and_back_returns_the_interior():
    agg = _bare()
    zeros = torch.zeros(1, 8, *GRID.shape)
    # a quarter turn maps voxel centres onto voxel centres: everything comes back
    v = _volume(b=1, seed=4)
    there = agg(zeros, v, _pose(math.pi / 2)).fused
    back = agg(zeros, there, _pose(-math.pi / 2)).fused
    assert not torch.allclose(there, v, atol=1e-3)
    assert torch.allclose(back, v, atol=1e-5)
    # any angle: trilinear interpolation reproduces a linear field wherever both warps read inside the grid
    grid = GridSpec((-8, -8, -2, 8, 8, 2), 1.0)
    agg = StreamAggregation(8, 5, grid, refine=False, occupied_head=False, forecast_head=False)
    centres = grid.centers()
    field = (centres @ torch.randn(3, 8, generator=torch.Generator().manual_seed(5)) + 0.3).permute(3, 0, 1, 2)[None]
    zeros = torch.zeros_like(field)
    back = agg(zeros, agg(zeros, field, _pose(0.3)).fused, _pose(-0.3)).fused
    interior = centres[..., :2].norm(dim=-1) < 5.5  # 7.5 m (outermost centres) less one voxel diagonal
    assert int(interior.sum()) > 300
    assert torch.allclose(back[0][:, interior], field[0][:, interior], atol=1e-4)
    # the warp is the core's
    assert torch.equal(agg(zeros, field, _pose(0.3)).warped, warp_volume(field, grid, _pose(0.3)))


def test_cbam_follows_eqs_3_and_4_and_its_maps_lie_in_0_1():
    torch.manual_seed(0)
    net = RefineNet(16).eval()
    x = torch.randn(2, 16, 6, 5, 4)
    refined, att = net(x)
    assert att.channel.shape == (2, 16, 1, 1, 1) and att.spatial.shape == (2, 1, 6, 5, 4)
    for m in (att.channel, att.spatial):
        assert bool((m > 0).all() and (m < 1).all())
    out = net.bottleneck(x)

    def mlp(v):  # the shared channel MLP: 1x1x1 conv, ReLU, 1x1x1 conv, no biases
        return F.conv3d(F.relu(F.conv3d(v, net.channel_mlp[0].weight)), net.channel_mlp[2].weight)

    mc = torch.sigmoid(mlp(out.mean((2, 3, 4), keepdim=True)) + mlp(out.amax((2, 3, 4), True)))
    assert torch.allclose(att.channel, mc)
    pooled = torch.cat([(mc * out).mean(1, keepdim=True), (mc * out).amax(1, keepdim=True)], 1)
    assert torch.allclose(att.spatial_logits, F.conv3d(pooled, net.spatial_conv.weight, padding=3))  # 7x7x7
    assert torch.allclose(refined, att.spatial * (mc * out) + x, atol=1e-6)  # Eq. 4


def test_reset_sample_takes_the_current_feature_itself_as_history():
    v_curr = _volume(seed=6).requires_grad_(True)
    v_hist = _volume(seed=7)
    motion = _pose(0.4, t=(1.3, -0.2, 0.0), batch=2)
    reset = torch.tensor([True, False])
    out = _bare()(v_curr, v_hist, motion, reset)
    assert torch.equal(out.warped[0], v_curr[0].detach())  # the public code: V_curr, unwarped, not zeros
    assert torch.equal(out.warped[1], warp_volume(v_hist, GRID, motion)[1])
    assert torch.equal(out.fused[0], 2 * v_curr[0].detach())
    out.fused.sum().backward()  # the history is detached, also where it is V_curr
    assert torch.equal(v_curr.grad, torch.ones_like(v_curr))
    # no history at all: every sample restarts
    assert torch.equal(_bare()(v_curr).warped, v_curr.detach())


def test_auxiliary_heads_run_in_training_only_and_switch_off():
    torch.manual_seed(0)
    agg = StreamAggregation(16, 5, GRID, upsample=2)
    v = torch.randn(2, 16, *GRID.shape)
    out = agg.train()(v, v.roll(1, 2), _pose(batch=2))
    assert out.occupied_logits.shape == (2, 16, 16, 8)
    assert out.forecast_logits.shape == (2, 5, 16, 16, 8)
    labels = torch.randint(0, 5, (2, 16, 16, 8))
    losses = agg.aux_losses(out, labels, free_label=4)
    assert set(losses) == {"occupied", "forecast"} and all(torch.isfinite(x) for x in losses.values())
    losses["occupied"].backward()  # the occupied head supervises RefineNet through M_s
    assert agg.refine.spatial_conv.weight.grad.abs().sum() > 0 and agg.forecast.net[0].weight.grad is None
    out = agg.eval()(v, v, _pose(batch=2))
    assert out.occupied_logits is None and out.forecast_logits is None
    cat = StreamAggregation(16, 5, GRID, fusion="concat", occupied_head=False, forecast_head=False, upsample=1)
    out = cat.train()(v, v, _pose(batch=2))
    assert out.fused.shape == v.shape and out.occupied_logits is None and out.forecast_logits is None
    with pytest.raises(ValueError, match="refine=True"):
        StreamAggregation(16, 5, GRID, refine=False)
    with pytest.raises(ValueError, match="fusion"):
        StreamAggregation(16, 5, GRID, fusion="mean")


def test_occupied_loss_is_plain_bce_with_logits():
    g = torch.Generator().manual_seed(8)
    logits = torch.randn(2, 3, 3, 2, generator=g)
    labels = torch.randint(0, 4, (2, 3, 3, 2), generator=g)
    target = (labels != 3).float()
    assert torch.allclose(
        occupied_loss(logits, labels, free_label=3), F.binary_cross_entropy_with_logits(logits, target)
    )
    mask = torch.rand(2, 3, 3, 2, generator=g) > 0.5
    ref = F.binary_cross_entropy_with_logits(logits[mask], target[mask])
    assert torch.allclose(occupied_loss(logits, labels, 3, mask=mask), ref)
    # one sigmoid: a confident right logit costs ~0 (a second sigmoid would leave >= log(1 + e^-1) = 0.31)
    assert float(occupied_loss(torch.full((1, 1, 1, 1), 20.0), torch.zeros(1, 1, 1, 1, dtype=torch.long), 3)) < 1e-6
    logits5 = torch.randn(2, 4, 3, 3, 2, generator=g)
    assert torch.allclose(forecast_loss(logits5, labels), F.cross_entropy(logits5, labels))


# ---------------------------------------------------------------------------------------------- boxes


def test_point_in_rotated_box():
    # a 2 x 2 x 2 box turned 45 degrees: a diamond |x| + |y| <= sqrt(2) in the footprint
    diamond = torch.tensor([[0.0, 0.0, 0.0, 2.0, 2.0, 2.0, math.pi / 4]])
    pts = torch.tensor(
        [
            [1.3, 0.0, 0.0],  # inside the diamond, outside the unrotated square
            [0.0, -1.35, 0.5],
            [0.7, 0.7, -0.9],  # |x| + |y| = 1.4
            [0.9, 0.6, 0.0],  # inside the unrotated square, outside the diamond
            [0.75, 0.75, 0.0],
            [0.0, 0.0, 1.2],  # above
        ]
    )
    assert points_in_boxes(pts, diamond)[:, 0].tolist() == [True, True, True, False, False, False]
    # a long thin box along +45 degrees (yaw turns +x towards +y), off the origin
    stick = torch.tensor([[1.0, 2.0, 0.0, 4.0, 0.5, 1.0, math.pi / 4]])
    pts = torch.tensor([[2.0, 3.0, 0.0], [0.0, 1.0, 0.2], [2.0, 1.0, 0.0], [0.0, 3.0, 0.0], [2.5, 3.5, 0.0]])
    assert points_in_boxes(pts, stick)[:, 0].tolist() == [True, True, False, False, False]
    both = points_in_boxes(pts[None].expand(2, -1, -1), torch.stack([stick, diamond]))  # batched
    assert both.shape == (2, 5, 1) and both[0, :, 0].tolist() == [True, True, False, False, False]


def test_box_iou_3d_known_values_and_invariances():
    boxes = torch.tensor(
        [
            [0.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.0],
            [0.0, 0.0, 0.0, 2.0, 2.0, 2.0, math.pi / 4],  # overlap with the first: a regular octagon
            [1.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.0],  # half of each
            [5.0, 5.0, 0.0, 1.0, 1.0, 1.0, 0.0],  # apart
            [0.0, 0.0, 1.0, 2.0, 2.0, 2.0, 0.0],  # half the height
        ],
        dtype=torch.float64,
    )
    iou = box_iou_3d(boxes, boxes)
    assert torch.allclose(iou.diagonal(), torch.ones(5, dtype=torch.float64))
    assert math.isclose(iou[0, 1], 1 / math.sqrt(2), rel_tol=1e-9)
    assert math.isclose(iou[0, 2], 1 / 3, rel_tol=1e-9) and math.isclose(iou[0, 4], 1 / 3, rel_tol=1e-9)
    assert iou[0, 3] == 0 and iou[1, 3] == 0
    g = torch.Generator().manual_seed(9)
    centre, size, yaw = (
        torch.rand(8, 3, generator=g) * 2 - 1,
        torch.rand(8, 3, generator=g) + 0.5,
        torch.rand(8, 1, generator=g),
    )
    rand = torch.cat([centre, size, yaw * 6 - 3], 1).double()
    iou = box_iou_3d(rand, rand)
    assert torch.allclose(iou, iou.T, atol=1e-12)
    moved = rand.clone()  # the same rigid motion of both boxes keeps the IoU
    moved[:, :2] = rand[:, :2] @ rotation_z(torch.tensor(0.7, dtype=torch.float64))[:2, :2].T + 3.0
    moved[:, 6] += 0.7
    assert torch.allclose(box_iou_3d(moved, moved), iou, atol=1e-9)
    # equal heights: the IoU is the footprints' area IoU; count 1 cm raster cells
    flat = rand.clone()
    flat[:, 2], flat[:, 5] = 0.0, 1.0
    xs = torch.arange(-3.0, 3.0, 0.01, dtype=torch.float64) + 0.005
    cells = torch.stack(torch.meshgrid(xs, xs, torch.zeros(1, dtype=torch.float64), indexing="ij"), -1).view(-1, 3)
    inside = points_in_boxes(cells, flat).double()  # (P, 8)
    inter = inside.T @ inside
    raster = inter / (inside.sum(0)[:, None] + inside.sum(0)[None] - inter)
    assert float((box_iou_3d(flat, flat) - raster).abs().max()) < 0.003


# ---------------------------------------------------------------------------------------------- matching


def test_hungarian_match_recovers_a_permutation_and_handles_no_ground_truth():
    g = torch.Generator().manual_seed(10)
    centre, size, yaw = (
        torch.rand(3, 3, generator=g) * 20,
        torch.rand(3, 3, generator=g) + 1,
        torch.rand(3, 1, generator=g),
    )
    gt = torch.cat([centre, size, yaw, torch.zeros(3, 2)], 1)  # 9 columns: zero velocity
    labels = torch.tensor([0, 2, 1])
    perm = torch.tensor([4, 0, 2])  # ground truth g is predicted by query perm[g]
    pred = torch.randn(5, 9, generator=g).abs() + 1
    pred[perm] = gt + 0.01
    logits = torch.full((5, 3), -4.0)
    logits[perm, labels] = 4.0
    enc_pred, enc_gt = encode_boxes(pred), encode_boxes(gt)
    matches = hungarian_match(
        torch.stack([logits, logits]), torch.stack([enc_pred, enc_pred]), [labels, labels[:0]], [enc_gt, enc_gt[:0]]
    )
    (p, t), (p0, t0) = matches
    assert p.tolist() == sorted(perm.tolist()) and perm[t].tolist() == p.tolist()
    assert p0.numel() == 0 and t0.numel() == 0 and p0.dtype == torch.int64
    # the cost is Sparse4D's: 2 x focal-style class cost + 0.25 x weighted L1
    cost = matching_cost(logits, enc_pred, labels, enc_gt)
    prob = logits.sigmoid()[:, labels]
    cls = 0.25 * (1 - prob) ** 2 * -(prob + 1e-12).log() - 0.75 * prob**2 * -(1 - prob + 1e-12).log()
    w = torch.tensor([2.0, 2, 2, 0.5, 0.5, 0.5, 0, 0, 0, 0])
    box = ((enc_pred[:, None] - enc_gt[None]).abs() * w).sum(-1)
    assert torch.allclose(cost, 2.0 * cls + 0.25 * box, atol=1e-5)


# ---------------------------------------------------------------------------------------------- DQA


def test_select_queries_paper_and_code_rules():
    gt = [torch.tensor([[0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0], [10.0, 0.0, 0.0, 0.5, 0.5, 1.7, 0.0]])]
    boxes = torch.tensor(
        [
            [
                [0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],  # exact car
                [0.9, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],  # car shifted 0.9 m: IoU 0.63
                [1.6, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],  # shifted 1.6 m: IoU 0.43
                [2.1, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],  # shifted 2.1 m: IoU 0.31
                [10.5, 0.0, 0.0, 0.5, 0.5, 1.7, 0.0],  # pedestrian 0.5 m off: IoU 0
                [11.0, 0.0, 0.0, 0.5, 0.5, 1.7, 0.0],  # pedestrian 1.0 m off
                [0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],  # exact, low score
            ]
        ]
    )
    scores = torch.tensor([[0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.2]])
    classes = torch.tensor([[0, 0, 0, 0, 1, 1, 0]])
    assert select_queries(scores, boxes).tolist() == [[True] * 6 + [False]]  # inference: score > 0.3
    paper = select_queries(scores, boxes, classes, gt_boxes=gt, small_classes=[1], **PAPER_SELECTION)
    assert paper.tolist() == [[True, True, True, False, True, False, False]]  # IoU > 0.4 / 2 Dc + Ds < 1.5
    by_size = select_queries(scores, boxes, classes, gt_boxes=gt, small_size=2.0, **PAPER_SELECTION)
    assert torch.equal(by_size, paper)
    code = select_queries(scores, boxes, classes, gt_boxes=gt, **CODE_SELECTION)
    assert code.tolist() == [[True, True, True, True, True, True, False]]  # cost 0.5 Dc < 1.5 or IoU > 0.3
    assert select_queries(scores, boxes, gt_boxes=gt, max_queries=2, **CODE_SELECTION).tolist() == [
        [True, True] + [False] * 5
    ]
    assert not select_queries(scores, boxes, gt_boxes=[gt[0][:0]], **CODE_SELECTION).any()  # no ground truth


def _dqa_case():
    torch.manual_seed(0)
    dqa = DynamicQueryAggregation(16, GRID, query_channels=12, heads=2)
    volume = torch.randn(2, 16, *GRID.shape)
    queries = torch.randn(2, 3, 12)
    boxes = torch.tensor(
        [
            [0.5, 0.5, 0.0, 3.0, 2.0, 2.0, 0.3],  # selected
            [1.5, 0.5, 0.0, 2.0, 2.0, 2.0, 0.0],  # selected, overlapping the first
            [-2.5, -2.5, 0.0, 2.0, 2.0, 2.0, 0.0],  # not selected
        ]
    ).expand(2, 3, 7)
    selected = torch.tensor([[True, True, False], [False, False, False]])
    return dqa, volume, queries, boxes, selected


def test_dqa_leaves_uncovered_voxels_bit_for_bit_and_changes_covered_ones():
    dqa, volume, queries, boxes, selected = _dqa_case()
    out = dqa(volume, queries, boxes, selected)
    centres = GRID.centers().view(-1, 3)
    member = points_in_boxes(centres, boxes[0, :2])  # (N, 2)
    covered = member.any(-1).view(GRID.shape)
    assert 0 < int(covered.sum()) < covered.numel() and bool((member.sum(-1) == 2).any())
    assert torch.equal(out[0][:, ~covered], volume[0][:, ~covered])  # Eq. 10, incl. the unselected box
    assert bool((out[0][:, covered] != volume[0][:, covered]).any(0).all())
    assert torch.equal(out[1], volume[1])  # nothing selected
    # the edge list (box index ranges, then the exact test) equals the brute-force membership
    vi, qi = dqa.edges(boxes[0, :2])
    assert sorted(zip(vi.tolist(), qi.tolist(), strict=True)) == sorted(map(tuple, member.nonzero().tolist()))
    # the code's coverage: every voxel of the rounded axis-aligned range, a superset here
    aabb = DynamicQueryAggregation(16, GRID, query_channels=12, heads=2, coverage="aabb")
    assert set(aabb.edges(boxes[0, :2])[0].tolist()) >= set(vi.tolist())


def test_dqa_matches_eqs_7_to_10_at_a_voxel_of_two_boxes():
    dqa, volume, queries, boxes, selected = _dqa_case()
    out = dqa(volume, queries, boxes, selected)
    member = points_in_boxes(GRID.centers(), boxes[0, :2])  # (X, Y, Z, 2)
    i, j, k = (member.all(-1)).nonzero()[0].tolist()
    v = volume[0, :, i, j, k]
    pe = torch.cat([dqa.pos[0][i], dqa.pos[1][j], dqa.pos[2][k]])
    q = dqa.w_q(v + pe).view(2, 8)
    keys = dqa.w_k(queries[0, :2]).view(2, 2, 8)  # (query, head, d)
    values = dqa.w_v(queries[0, :2]).view(2, 2, 8)
    alpha = torch.einsum("hd,jhd->hj", q, keys).div(math.sqrt(8)).softmax(-1)
    z = torch.einsum("hj,jhd->hd", alpha, values).reshape(16)
    gate = torch.sigmoid(dqa.w_gate(torch.cat([v, z])))
    assert torch.allclose(out[0, :, i, j, k], v + gate * z, atol=1e-5)
    out.sum().backward()
    assert dqa.w_k.weight.grad.abs().sum() > 0 and dqa.pos[0].grad.abs().sum() > 0


@pytest.mark.parametrize("coverage", ["center", "aabb"])
def test_dqa_dense_path_equals_the_edge_list(coverage, monkeypatch):
    """The traceable dense path (export, torch.compile) computes the edge list's result: same membership, same
    values and every gradient in float64, uncovered voxels bit for bit; a traced forward takes it."""
    torch.manual_seed(1)
    dqa = DynamicQueryAggregation(16, GRID, query_channels=12, heads=2, coverage=coverage).double()
    centre = torch.rand(3, 9, 3, dtype=torch.float64) * torch.tensor([10.0, 10.0, 2.0]) - torch.tensor([5.0, 5.0, 1.0])
    size = torch.rand(3, 9, 3, dtype=torch.float64) * 4 + 1.5
    yaw = torch.rand(3, 9, 1, dtype=torch.float64) * 2 * math.pi
    boxes = torch.cat([centre, size, yaw], -1)  # overlapping, some straddling the grid's edge
    boxes[:, 0, :3] = torch.tensor([9.0, 0.0, 0.0], dtype=torch.float64)  # wholly off the grid
    selected = torch.rand(3, 9) > 0.3
    selected[:, 0] = True
    selected[2] = False  # a sample with nothing selected
    member = dqa.membership(boxes, selected)
    for b in range(3):
        sel = selected[b].nonzero().flatten()
        vi, qi = dqa.edges(boxes[b, sel])
        pairs = sorted(zip(vi.tolist(), sel[qi].tolist(), strict=True))
        assert pairs == sorted(map(tuple, member[b].nonzero().tolist()))
    assert not member[:, :, 0].any() and not member[2].any()
    for b in range(2):  # both active samples cover voxels, some of them by two boxes or more
        assert bool(member[b].any(-1).any()) and bool((member[b].sum(-1) >= 2).any())
    assert dqa.membership(boxes[:, :0], selected[:, :0]).shape == (3, GRID.shape[0] * GRID.shape[1] * GRID.shape[2], 0)

    def run(path):
        torch.manual_seed(2)
        volume = torch.randn(3, 16, *GRID.shape, dtype=torch.float64, requires_grad=True)
        queries = torch.randn(3, 9, 12, dtype=torch.float64, requires_grad=True)
        dqa.zero_grad()
        out = path(volume, queries, boxes, selected)
        (out * torch.randn_like(out)).sum().backward()
        return out, volume, [volume.grad, queries.grad, *(p.grad for p in dqa.parameters())]

    (sparse, volume, g_sparse), (dense, _, g_dense) = run(dqa.sparse), run(dqa.dense)
    assert torch.allclose(dense, sparse, rtol=0, atol=1e-12)
    assert len(g_dense) == 2 + len(list(dqa.parameters()))
    for a, b in zip(g_dense, g_sparse, strict=True):
        assert a is not None and torch.isfinite(a).all() and torch.allclose(a, b, rtol=0, atol=1e-12)
    uncovered = ~member.any(-1).view(3, *GRID.shape)
    assert torch.equal(dense.detach().movedim(1, -1)[uncovered], volume.detach().movedim(1, -1)[uncovered])
    assert torch.equal(dense[2], volume[2])
    # an unselected query never enters, whatever its features
    poisoned = torch.randn(3, 9, 12, dtype=torch.float64)
    clean = dqa.dense(volume, poisoned, boxes, selected)
    poisoned[~selected] = math.inf
    assert torch.equal(dqa.dense(volume, poisoned, boxes, selected), clean)
    monkeypatch.setattr(torch.compiler, "is_compiling", lambda: True)
    calls = []
    monkeypatch.setattr(dqa, "dense", lambda *a: calls.append(1) or dqa.sparse(*a))
    dqa(volume, torch.randn(3, 9, 12, dtype=torch.float64), boxes, selected)
    assert calls == [1]


def test_voxel_ffn_shape_and_residual():
    ffn = VoxelFFN(16, final_norm=False)
    torch.nn.init.zeros_(ffn.mlp[2].weight)
    torch.nn.init.zeros_(ffn.mlp[2].bias)
    v = torch.randn(1, 16, 3, 2, 2)
    assert torch.equal(ffn(v), v)  # the residual path alone
    assert VoxelFFN(16)(v).shape == v.shape
