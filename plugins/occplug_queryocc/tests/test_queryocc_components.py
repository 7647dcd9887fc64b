"""QueryOcc's pieces against their definitions (QueryOcc §3, Eq. 1-3)."""

import math

import pytest
import torch

from occplug.data import LabelledPoints
from occplug.geometry import GridSpec, contract, invert_pose, transform_points, uncontract
from occplug.interfaces import BevScene
from occplug.testing import make_tiny_batch
from occplug_queryocc import QueryDecoder, log_linear_depths, sample_queries, supervision_points, visibility
from occplug_queryocc.supervision import QuerySupervision


def test_contraction_is_continuous_monotone_bounded_and_invertible():
    x = torch.linspace(-500.0, 500.0, 200001, dtype=torch.float64)
    y = contract(x, near=24.0, kappa=0.8)
    assert bool((y.diff() > 0).all())  # strictly monotone
    assert float(y.abs().max()) < 1.0
    assert float(y.diff().abs().max()) < 1e-3  # no jump (steps of 5 mm in x)
    at = torch.tensor([24.0 - 1e-9, 24.0 + 1e-9], dtype=torch.float64)
    assert torch.allclose(contract(at, 24.0, 0.8), torch.tensor([0.8, 0.8], dtype=torch.float64), atol=1e-9)
    assert torch.allclose(uncontract(y, 24.0, 0.8), x, rtol=1e-9, atol=1e-9)
    grid = GridSpec((-30, -30, -1, 30, 30, 5.4), (1.0, 1.0, 6.4), contraction={"near": 24.0, "kappa": 0.8})
    pts = torch.tensor([[1.0, -2.0, 0.3], [150.0, -900.0, 2.0]], dtype=torch.float64)
    assert torch.allclose(grid.denormalize(grid.normalize(pts)), pts, rtol=1e-9)


def test_depth_bins_hit_near_and_far_and_uniform_is_linear():
    d = log_linear_depths(16, 1.0, 80.0, 0.0)
    assert d[0] == 1.0 and d[-1] == 80.0 and bool((d.diff() > 0).all())
    ratio = d[1:] / d[:-1]
    assert torch.allclose(ratio, ratio[0].expand_as(ratio), rtol=1e-5)  # geometric
    assert torch.allclose(log_linear_depths(16, 1.0, 80.0, 1.0), torch.linspace(1.0, 80.0, 16))
    mix = log_linear_depths(5, 2.0, 50.0, 0.3)
    r = torch.linspace(0, 1, 5, dtype=torch.float64)
    ref = 0.7 * 2.0 * 25.0**r + 0.3 * (2.0 + r * 48.0)
    assert torch.allclose(mix.double(), ref, rtol=1e-6)


def test_visibility_is_one_minus_the_mass_in_front():
    p = torch.tensor([0.1, 0.2, 0.3, 0.4]).view(1, 1, 4, 1, 1)
    assert torch.allclose(visibility(p).flatten(), torch.tensor([1.0, 0.9, 0.7, 0.4]))


def _points(n=50, seed=0):
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(n, 3, generator=g)
    p = o + torch.randn(n, 3, generator=g) * 10
    return LabelledPoints(p, o, torch.randint(0, 17, (n,), generator=g))


def test_negatives_lie_between_origin_and_point_and_positives_within_zeta_behind():
    pts = _points()
    zeta = 0.5
    q = sample_queries([(pts, torch.zeros(len(pts)))], 400, 3, 2, zeta, 255, torch.Generator().manual_seed(1))
    assert q.points.shape == (1, 400 * 5, 3)
    # recover each query's source point: the sampler draws `pick` first with the same generator
    pick = torch.randint(0, len(pts), (400,), generator=torch.Generator().manual_seed(1))
    p, o = pts.points[pick], pts.origins[pick]
    neg = q.points[0, : 400 * 3].view(400, 3, 3)
    pos = q.points[0, 400 * 3 :].view(400, 2, 3)
    ray = p - o
    length = ray.norm(dim=-1, keepdim=True)
    s_neg = ((neg - o[:, None]) * ray[:, None]).sum(-1) / length.square()  # position along the ray in [0, 1]
    assert bool((s_neg > 0).all()) and bool((s_neg < 1).all())
    assert torch.allclose(neg, o[:, None] + s_neg[..., None] * ray[:, None], atol=1e-4)  # on the segment
    behind = ((pos - p[:, None]) * (ray / length)[:, None]).sum(-1)
    assert bool((behind >= 0).all()) and bool((behind < zeta).all())
    assert torch.allclose(pos, p[:, None] + behind[..., None] * (ray / length)[:, None], atol=1e-4)
    assert not bool(q.occupied[0, : 400 * 3].any()) and bool(q.occupied[0, 400 * 3 :].all())
    assert bool((q.labels[0, : 400 * 3] == 255).all())
    assert torch.equal(q.labels[0, 400 * 3 :], pts.labels[pick].repeat_interleave(2))


def _box_contains(boxes, pts, margin=0.3):
    """(P,) whether each ego point lies in any (M, 9) box (yaw about z), grown by margin."""
    inside = torch.zeros(len(pts), dtype=torch.bool)
    for box in boxes:
        c, size, yaw = box[:3], box[3:6], box[6]
        d = pts - c
        cos, sin = math.cos(-yaw), math.sin(-yaw)
        local = torch.stack([cos * d[:, 0] - sin * d[:, 1], sin * d[:, 0] + cos * d[:, 1], d[:, 2]], -1)
        inside |= (local.abs() <= size / 2 + margin).all(-1)
    return inside


def _later_frames(offsets):
    """Frames 1 and 2 of the tiny world's first scene (frame 0 has no previous frame) with perfect pseudo labels."""
    from occplug.data import collate_frames
    from occplug.data.synthetic import SyntheticDataModule

    dm = SyntheticDataModule(preset="tiny", adjacent_offsets=offsets, pseudo_labels={"synthetic": "perfect"})
    ds = dm.dataset("train")
    return collate_frames([ds[1], ds[2]])


def test_points_of_the_previous_frame_land_in_the_current_ego_frame():
    batch = _later_frames([-1])
    sets = supervision_points(batch, "pseudo", [-1], 255)
    prev = batch.adjacent[-1]
    for i, (pts, times) in enumerate(sets):
        moved = float((invert_pose(batch.ego_to_global[i].double()) @ prev.ego_to_global[i].double())[:3, 3].norm())
        assert moved > 1.0  # the ego drove between the frames: the transform is not the identity
        dt = float(prev.timestamp[i] - batch.timestamp[i])
        assert dt < 0 and torch.allclose(times, torch.full_like(times, dt))
        # moving agents: points labelled as vehicles/pedestrians lie in that frame's boxes, moved into this frame
        to_cur = (invert_pose(batch.ego_to_global[i].double()) @ prev.ego_to_global[i].double()).float()
        boxes = prev.boxes[i].clone()
        boxes[:, :3] = transform_points(to_cur, boxes[:, :3])
        boxes[:, 6] += math.atan2(float(to_cur[1, 0]), float(to_cur[0, 0]))
        near = (pts.points[:, :2].abs() <= 10.0).all(-1)  # boxes are listed for agents near the label grid
        agent = torch.isin(pts.labels, prev.box_labels[i].unique()) & near  # the classes that have boxes
        if bool(agent.any()):
            assert _box_contains(boxes, pts.points[agent]).float().mean() > 0.97
        # static structure lands on itself: the ground seen at t-1 is the ground now (z = 0 in this world)
        ground = pts.labels == 11
        assert bool(ground.any())
        assert float(pts.points[ground, 2].abs().max()) < 0.05
        # and in x-y: seen at t-1, static structure (buildings) lands in voxels occupied now
        grid = GridSpec((-16.0, -16.0, -1.0, 16.0, 16.0, 5.4), 0.8)
        building = (pts.labels == 15) & grid.contains(pts.points)
        if bool(building.any()):
            idx = grid.coord_to_index(pts.points[building])
            labels = batch.voxel_labels[i][idx[:, 0], idx[:, 1], idx[:, 2]]
            assert (labels != 17).float().mean() > 0.9


def test_a_sample_without_points_adds_nothing_to_the_losses():
    full = _points(20)
    empty = LabelledPoints(torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0, dtype=torch.int64))
    q = sample_queries([(full, torch.zeros(20)), (empty, torch.zeros(0))], 16, 2, 2, 0.5, 255)
    assert bool(q.valid[0].all()) and not bool(q.valid[1].any())
    source = QuerySupervision(points_per_sample=16, negatives=2, positives=2)
    source.queries = lambda batch: q  # the drawn set above, through the source's losses
    from occplug.interfaces import ModelOutputs, QueryResult

    def answer(name, points, times=None):  # a field that gets sample 1 (the placeholders) maximally wrong
        o = torch.zeros(points.shape[:2])
        o[1] = torch.where(q.occupied[1], -30.0, 30.0)
        return QueryResult(class_logits=torch.zeros(*points.shape[:2], 18), occupancy_logit=o)

    losses = source(None, ModelOutputs(None, None, None, {}, answer))
    assert float(losses["occ"]) == pytest.approx(math.log(2.0), rel=1e-5)  # sample 0's BCE at o = 0 only


def test_decoder_outputs_at_voxel_centres_equal_predict_occupancy():
    grid = GridSpec((-16, -16, -1, 16, 16, 5.4), 0.8)
    bev = GridSpec((-20, -20, -1, 20, 20, 5.4), (1.0, 1.0, 6.4), contraction={"near": 16.0, "kappa": 0.8})
    head = QueryDecoder(8, 18, hidden=16, occupancy_threshold=0.3).eval()
    scene = BevScene(torch.randn(1, 8, *bev.shape[:2]), bev)
    logits = head.occupancy_logits(scene, grid)
    pred = logits.argmax(1)
    centres = grid.centers().reshape(1, -1, 3)
    res = head.query(scene, centres)
    occupied = torch.sigmoid(res.occupancy_logit) >= 0.3
    cls = res.class_logits.clone()
    cls[..., 17] = -torch.inf
    expected = torch.where(occupied, cls.argmax(-1), torch.full_like(occupied, 17, dtype=torch.int64))
    agree = (pred.reshape(1, -1) == expected).float().mean()
    assert agree > 0.999  # ties at exactly the threshold aside


def test_the_model_predicts_what_its_decoder_answers_at_the_voxel_centres():
    from occplug.run.runner import build_datamodule, build_model, load_config

    cfg = load_config(["queryocc/base"], ["data.preset=tiny", "model.heads.occupancy.occupancy_threshold=0.4"])
    dm = build_datamodule(cfg)
    dm.prepare_data()
    dm.setup("fit")
    model = build_model(cfg, dm).eval()
    batch = make_tiny_batch(1, pseudo_labels="default")
    pred = model.predict_occupancy(batch)  # (1, X, Y, Z) through the model's evaluation path
    with torch.no_grad():
        outputs = model(batch)
        res = model.heads["occupancy"].query(outputs.scene, model.grid.centers().reshape(1, -1, 3))
    p = torch.sigmoid(res.occupancy_logit)
    cls = res.class_logits.clone()
    cls[..., 17] = -torch.inf
    expected = torch.where(p >= 0.4, cls.argmax(-1), torch.full_like(p, 17, dtype=torch.int64))
    clear = (p - 0.4).abs() > 1e-5  # a voxel exactly at the threshold may go either way
    assert torch.equal(pred.reshape(1, -1)[clear], expected[clear])


def test_query_supervision_loss_falls_on_one_batch():
    batch = make_tiny_batch(1, pseudo_labels="perfect")
    grid = GridSpec((-20, -20, -1, 20, 20, 5.4), (1.0, 1.0, 6.4), contraction={"near": 16.0, "kappa": 0.8})
    plane = torch.nn.Parameter(torch.zeros(1, 8, *grid.shape[:2]))
    head = QueryDecoder(8, 18, hidden=32)
    source = QuerySupervision(points_per_sample=256)
    opt = torch.optim.Adam([plane, *head.parameters()], lr=1e-2)
    from occplug.interfaces import ModelOutputs

    losses = []
    torch.manual_seed(0)
    for _ in range(40):
        scene = BevScene(plane, grid)
        out = ModelOutputs(None, None, scene, {}, lambda name, p, t=None, s=scene: head.query(s, p, t))
        loss = sum(source(batch, out).values())
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss))
    assert sum(losses[-5:]) / 5 < 0.7 * sum(losses[:5]) / 5


def test_long_range_off_drops_far_points():
    batch = make_tiny_batch(1, pseudo_labels="perfect")
    near = QuerySupervision(long_range=False, near_range=5.0, points_per_sample=512)
    q = near.queries(batch)
    pos = q.points[q.occupied]
    # positives sit within zeta behind a point inside the near field
    assert float(pos[:, :2].abs().max()) <= 5.0 + near.zeta + 1e-4


@pytest.mark.parametrize("source", ["lidar", "union"])
def test_lidar_points_take_their_class_from_the_pseudo_semantics(source):
    batch = make_tiny_batch(1, pseudo_labels="perfect")
    ((pts, _),) = supervision_points(batch, source, [0], 255)
    seen = pts.labels != 255
    assert seen.float().mean() > 0.2
    # perfect pseudo semantics: the projected class is the point's own label where a camera sees it
    from occplug.data import lidar_points

    lid = lidar_points(batch)[0]
    ref = batch.point_labels[0]
    ok = lid.labels != 255
    assert (lid.labels[ok] == ref[ok]).float().mean() > 0.85


@pytest.mark.parametrize(
    ("name", "half", "cells"), [("no_contraction", 60.0, 60), ("no_contraction_near", 24.0, 60), ("base", 30.0, 60)]
)
def test_the_contraction_ablations_lay_a_metric_plane_of_the_same_cells(name, half, cells):
    """The ablation must drop the base's contraction (an overlay that changes only the range keeps it, and a
    contracted plane's cells do not depend on its numeric range: it trained identically to base)."""
    from occplug.run.runner import load_config

    grid = GridSpec.from_config(load_config([f"queryocc/{name}"], [])["model"]["view_transform"]["grid"])
    assert grid.shape[:2] == (cells, cells)
    assert (grid.contraction is None) == (name != "base")
    if grid.contraction is None:  # metric: a point at 0.9 of the half-range lies in the cell that range says
        index = grid.coord_to_index(torch.tensor([[0.9 * half, 0.0, 0.0]]))
        assert int(index[0, 0]) == int(0.95 * cells)


def test_checkpointed_query_chunks_give_the_values_and_gradients_of_one_pass():
    torch.manual_seed(0)
    bev = GridSpec((-20, -20, -1, 20, 20, 5.4), (1.0, 1.0, 6.4), contraction={"near": 16.0, "kappa": 0.8})
    plain = QueryDecoder(8, 18, hidden=16, offsets=3, num_blocks=2, feature_dim=5)
    chunked = QueryDecoder(8, 18, hidden=16, offsets=3, num_blocks=2, feature_dim=5, checkpoint_queries=7)
    chunked.load_state_dict(plain.state_dict())
    points = torch.rand(2, 30, 3) * torch.tensor([40.0, 40.0, 6.4]) - torch.tensor([20.0, 20.0, 1.0])
    times = torch.tensor([-0.5, 0.0, 0.5]).repeat(2, 10)
    results, grads = [], []
    for head in (plain, chunked):
        plane = torch.randn(2, 8, *bev.shape[:2], generator=torch.Generator().manual_seed(1)).requires_grad_()
        res = head.query(BevScene(plane, bev), points, times)
        loss = res.occupancy_logit.square().sum() + res.class_logits.sin().sum() + res.features.cos().sum()
        loss.backward()
        results.append(res)
        grads.append([plane.grad, *(p.grad for p in head.parameters())])
    for a, b in zip((results[0].occupancy_logit, results[0].class_logits, results[0].features),
                    (results[1].occupancy_logit, results[1].class_logits, results[1].features), strict=True):  # fmt: skip
        assert a.shape == b.shape and torch.allclose(a, b, rtol=1e-5, atol=1e-6)
    for a, b in zip(*grads, strict=True):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-6)
    with torch.no_grad():  # without gradients: one pass whatever the setting
        assert torch.equal(chunked.query(BevScene(plane, bev), points, times).occupancy_logit,
                           plain.query(BevScene(plane, bev), points, times).occupancy_logit)  # fmt: skip
