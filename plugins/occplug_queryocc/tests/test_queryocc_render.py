"""queryocc_render_points: QueryOcc's rendering-only baseline -- exact alpha blending, the query budget of queryocc_query_points,
a ground-truth field renders the true depth, a small decoder learns from it, and it trains beside queryocc_query_points."""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path

import pytest
import torch
from torch import Tensor, nn

from occplug.data import Batch
from occplug.geometry import GridSpec, camera_rays, invert_pose, transform_points
from occplug.interfaces import BevScene, ModelOutputs, QueryResult
from occplug.testing import check_component, hand_batch, make_tiny_batch, run_config
from occplug_queryocc import QuerySupervision, RenderSupervision
from occplug_queryocc.heads import QueryDecoder
from occplug_queryocc.supervision import render_rays, transmittance_weights

# The field of test 1: a voxel grid whose ground slab's top (z = 0) and wall's face (x = 8) are voxel faces.
FIELD = GridSpec((-48.0, -48.0, -0.8, 48.0, 48.0, 12.0), 0.8)
GROUND_BOX = ((-48.0, -48.0, -0.8), (48.0, 48.0, 0.0))
WALL_BOX = ((8.0, -48.0, 0.0), (8.8, 48.0, 12.0))  # too high for any ray to clip its top
GROUND_CLASS, WALL_CLASS = 11, 15  # driveable_surface, manmade (free = 17)


def tiny_pseudo_batch() -> Batch:
    """Two frames of the tiny world with its default (imperfect) pseudo labels and the frames at -1 and +1."""
    return make_tiny_batch(2, adjacent_offsets=[-1, 1], pseudo_labels="default")


def _outputs(query) -> ModelOutputs:
    return ModelOutputs(image_features=None, lifted=None, scene=None, heads={}, query=query)


# ---------------------------------------------------------------- 1: a ground-truth field renders the true depth
def _box_entry(origins: Tensor, dirs: Tensor, box) -> Tensor:
    """Range along unit rays where each enters an axis-aligned box (inf: missed; origins lie outside)."""
    lo, hi = (torch.tensor(v, dtype=dirs.dtype) for v in box)
    safe = torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    t1, t2 = (lo - origins) / safe, (hi - origins) / safe
    t_in, t_out = torch.minimum(t1, t2).amax(-1), torch.maximum(t1, t2).amin(-1)
    return torch.where((t_out >= t_in) & (t_in > 0), t_in, torch.full_like(t_in, math.inf))


def _with_true_pseudo_labels(batch: Batch, max_depth: float) -> Batch:
    """``batch`` (and its adjacent frames) with pseudo depth / semantics of the wall-and-ground world, ray cast
    exactly through ``camera_rays`` (camera z; 0 where no surface within ``max_depth``)."""

    def relabel(frame: Batch) -> Batch:
        n, _, h, w = frame.images.shape[1:]
        origins, dirs, z_per_metre = camera_rays(frame.intrinsics, frame.cam_to_ego, h, w, frame.img_aug)
        depth = torch.zeros(len(frame), n, h, w)
        labels = torch.full((len(frame), n, h, w), 255, dtype=torch.int64)
        for i in range(len(frame)):
            to_current = (invert_pose(batch.ego_to_global[i].double()) @ frame.ego_to_global[i].double()).float()
            o = transform_points(to_current, origins[i])[:, None, None].expand(n, h, w, 3)
            d = (dirs[i].reshape(-1, 3) @ to_current[:3, :3].T).reshape(n, h, w, 3)
            assert (o[..., 0] < WALL_BOX[0][0]).all() and (o[..., 2] > 0).all(), "cameras must face the wall"
            ground, wall = _box_entry(o, d, GROUND_BOX), _box_entry(o, d, WALL_BOX)
            z = torch.minimum(ground, wall) * z_per_metre[i]
            hit = z <= max_depth
            depth[i] = torch.where(hit, z, torch.zeros_like(z))
            labels[i] = torch.where(hit, torch.where(wall < ground, WALL_CLASS, GROUND_CLASS), labels[i])
        return dataclasses.replace(frame, pseudo_depth=depth, pseudo_semantics=labels)

    out = relabel(batch)
    return dataclasses.replace(out, adjacent={k: relabel(f) for k, f in batch.adjacent.items()})


def _field_query(head: str, points: Tensor, times: Tensor | None = None) -> QueryResult:
    """Occupancy logit +20 in the occupied voxels of FIELD (ground slab and wall), -20 elsewhere; class logits
    +10 for the voxel's class."""
    occ = torch.zeros(FIELD.shape, dtype=torch.bool)
    cls = torch.zeros(FIELD.shape, dtype=torch.int64)
    occ[:, :, 0], cls[:, :, 0] = True, GROUND_CLASS
    wall_x = round((WALL_BOX[0][0] - FIELD.range[0]) / FIELD.voxel_size[0])
    occ[wall_x, :, 1:], cls[wall_x, :, 1:] = True, WALL_CLASS
    origin, size = torch.tensor(FIELD.range[:3]), torch.tensor(FIELD.voxel_size)
    idx = ((points - origin) / size).floor().long()
    inside = ((idx >= 0) & (idx < torch.tensor(FIELD.shape))).all(-1)
    idx = torch.minimum(idx.clamp_min(0), torch.tensor(FIELD.shape) - 1)
    hit = occ[idx[..., 0], idx[..., 1], idx[..., 2]] & inside
    labels = cls[idx[..., 0], idx[..., 1], idx[..., 2]]
    logits = torch.nn.functional.one_hot(labels, 18).float() * 10.0
    return QueryResult(class_logits=logits, occupancy_logit=torch.where(hit, 20.0, -20.0))


def test_a_ground_truth_field_renders_depth_within_one_voxel():
    """The tiny world's cameras and poses (current and adjacent frames) look at a wall and the ground of a known
    voxel grid; with pseudo depth = the true depth, every rendered depth is within one voxel of it."""
    batch = _with_true_pseudo_labels(tiny_pseudo_batch(), max_depth=30.0)
    source = RenderSupervision(
        frame_offsets=[-1, 0, 1], rays_per_sample=512, samples_per_ray=128, near=0.5, far=40.0, spacing="uniform"
    )  # bins of 0.31 m
    torch.manual_seed(0)
    rays = source.rays(batch)
    assert rays.valid.all()
    b, r, s = rays.depths.shape
    result = _field_query("occupancy", rays.points.reshape(b, r * s, 3))
    rendered = render_rays(
        result.occupancy_logit.reshape(b, r, s), result.class_logits.reshape(b, r, s, -1), rays.depths, source.far, 17
    )
    error = (rendered.depth - rays.target_depth).abs()
    assert error.max() < FIELD.voxel_size[0], f"worst depth error {error.max():.3f} m"
    # rays from every frame were drawn, with their frames' times (the -1 frame of sample 0 is itself)
    assert set(rays.times.unique().tolist()) == {-0.5, 0.0, 0.5}
    # wall and ground pixels both, and the rendered class is the true one (both lie below free: same index)
    # but where a ray meets the wall at its foot and its next sample is already in the ground below it
    assert set(rays.labels.unique().tolist()) == {GROUND_CLASS, WALL_CLASS}
    assert (rendered.log_probs.argmax(-1) == rays.labels).float().mean() > 0.99
    torch.manual_seed(0)
    losses = source(batch, _outputs(_field_query))
    relative = (rendered.depth - rays.target_depth).abs() / rays.target_depth
    torch.testing.assert_close(losses["depth"], relative.mean(), atol=0.05, rtol=0.5)  # another draw of rays
    assert losses["depth"] < 0.1 and losses["sem"] < 0.1


# ---------------------------------------------------------------- 2: transmittance and weights by hand
def _logit(p: float) -> float:
    return math.log(p / (1 - p))


def test_transmittance_and_weights_equal_a_hand_computed_example():
    o = torch.tensor([_logit(0.5), _logit(0.2), _logit(0.6)])
    alpha, t, w = transmittance_weights(o)
    torch.testing.assert_close(alpha, torch.tensor([0.5, 0.2, 0.6]))
    torch.testing.assert_close(t, torch.tensor([1.0, 0.5, 0.4]))
    torch.testing.assert_close(w, torch.tensor([0.5, 0.1, 0.24]))
    # K = 3 with free = 2 (its logit 100 must not matter): softmax over {0, 1} is (.75, .25), (.5, .5), (.25, .75)
    s = torch.tensor([[math.log(3), 0.0, 100.0], [0.0, 0.0, 100.0], [0.0, math.log(3), 100.0]])
    rendered = render_rays(o, s, torch.tensor([1.0, 2.0, 3.0]), far=10.0, free_label=2)
    torch.testing.assert_close(rendered.weights, w)
    torch.testing.assert_close(rendered.leftover, torch.tensor(0.16))  # 1 - (0.5 + 0.1 + 0.24), placed at far
    torch.testing.assert_close(rendered.depth, torch.tensor(0.5 * 1 + 0.1 * 2 + 0.24 * 3 + 0.16 * 10))
    torch.testing.assert_close(rendered.log_probs.exp(), torch.tensor([0.485, 0.355]) / 0.84)


def test_the_losses_equal_a_hand_computed_example():
    """One camera at the ego origin (identity geometry: ego = camera frame, so a point's z is its depth), one
    pixel at pseudo depth 5 of class 2 with free = 1: the label takes the second of the classes other than free."""
    batch = hand_batch(
        1,
        image_hw=(1, 1),
        pseudo_depth=torch.full((1, 1, 1, 1), 5.0),
        pseudo_semantics=torch.full((1, 1, 1, 1), 2, dtype=torch.int64),
    )
    seen = {}

    def query(head, points, times=None):
        seen["points"] = points
        o = torch.tensor([[_logit(0.5), _logit(0.2), _logit(0.6)]])
        s = torch.tensor([[[math.log(3), 100.0, 0.0], [0.0, 100.0, 0.0], [0.0, 100.0, math.log(3)]]])
        return QueryResult(class_logits=s, occupancy_logit=o)

    source = RenderSupervision(
        rays_per_sample=1, samples_per_ray=3, near=1.0, far=10.0, lambda_depth=2.0, free_label=1, spacing="uniform"
    )
    losses = source(batch, _outputs(query))
    z = seen["points"][0, :, 2]
    assert ((z >= torch.tensor([1.0, 4.0, 7.0])) & (z <= torch.tensor([4.0, 7.0, 10.0]))).all()  # one per bin
    assert torch.allclose(seen["points"][0, :, :2], torch.zeros(3, 2))  # pixel (0, 0) on the optical axis
    depth = 0.5 * z[0] + 0.1 * z[1] + 0.24 * z[2] + 0.16 * 10.0
    torch.testing.assert_close(losses["depth"], 2.0 * (depth - 5.0).abs() / 5.0)
    torch.testing.assert_close(losses["sem"], -torch.log(torch.tensor(0.355 / 0.84)))
    # a pixel of the ignore label (or of free) has no semantic term, and one deeper than far a depth target of far
    batch = dataclasses.replace(
        batch,
        pseudo_semantics=torch.full((1, 1, 1, 1), 255, dtype=torch.int64),
        pseudo_depth=torch.full((1, 1, 1, 1), 50.0),
    )
    losses = source(batch, _outputs(query))
    depth = 0.5 * seen["points"][0, 0, 2] + 0.1 * seen["points"][0, 1, 2] + 0.24 * seen["points"][0, 2, 2] + 1.6
    torch.testing.assert_close(losses["depth"], 2.0 * (10.0 - depth) / 10.0)
    assert losses["sem"] == 0


# ---------------------------------------------------------------- 3: the query budget of queryocc_query_points
@pytest.mark.parametrize("offsets", [[0], [-1, 0, 1]])
def test_queries_per_step_equal_rays_times_samples_and_query_points_default(offsets):
    render, queries = RenderSupervision(frame_offsets=offsets), QuerySupervision(frame_offsets=offsets)
    assert render.rays_per_sample * render.samples_per_ray == 256 * 32
    assert render.rays_per_sample * render.samples_per_ray == queries.points_per_sample * (
        queries.negatives + queries.positives
    )
    assert render.needs_temporal_queries == (offsets != [0]) == queries.needs_temporal_queries
    assert render.requires == {"pseudo_depth", "pseudo_semantics"} and render.requires <= queries.requires
    batch = tiny_pseudo_batch()
    counts = {}
    for name, source in (("render", render), ("queries", queries)):
        calls = []

        def query(head, points, times=None, calls=calls):
            calls.append((head, tuple(points.shape), None if times is None else tuple(times.shape)))
            b, p = points.shape[:2]
            return QueryResult(
                class_logits=torch.zeros(b, p, 18, requires_grad=True),
                occupancy_logit=torch.zeros(b, p, requires_grad=True),
            )

        losses = source(batch, _outputs(query))
        assert len(calls) == 1, "one query per step"
        head, shape, times = calls[0]
        assert head == "occupancy" and times == (None if offsets == [0] else shape[:2])
        counts[name] = shape[1]
        assert all(torch.isfinite(v) for v in losses.values())
    assert counts["render"] == counts["queries"] == 8192
    assert set(RenderSupervision()(batch, _outputs(query))) == {"depth", "sem"}  # queries returns occ and sem


def test_render_points_conforms_and_registers():
    source = check_component("supervision", "queryocc_render_points", batch=make_tiny_batch())
    assert isinstance(source, RenderSupervision) and source.query_head == "occupancy"


# ---------------------------------------------------------------- 4: a small decoder learns from rendering
def test_the_loss_falls_when_a_small_decoder_trains_on_one_batch():
    torch.manual_seed(0)
    batch = tiny_pseudo_batch()
    grid = GridSpec((-30.0, -30.0, -1.0, 30.0, 30.0, 5.4), (3.0, 3.0, 6.4), contraction={"near": 24.0, "kappa": 0.8})
    plane = nn.Parameter(0.1 * torch.randn(2, 8, *grid.shape[:2]))
    decoder = QueryDecoder(in_channels=8, num_classes=18, hidden=32, offsets=2, num_blocks=1)
    scene = BevScene(plane, grid)
    outputs = _outputs(lambda head, points, times=None: decoder.query(scene, points, times))
    source = RenderSupervision(frame_offsets=[-1, 0, 1], rays_per_sample=32, samples_per_ray=16)
    optimizer = torch.optim.Adam([plane, *decoder.parameters()], lr=0.01)
    history = []
    for _ in range(20):
        torch.manual_seed(1)  # the same rays every step
        losses = source(batch, outputs)
        loss = sum(losses.values())
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        history.append({k: float(v.detach()) for k, v in losses.items()})
    first, last = history[0], history[-1]
    assert last["depth"] < 0.5 * first["depth"], history
    assert last["sem"] < 0.7 * first["sem"], history


# ---------------------------------------------------------------- 5: both sources in one config train a step
def test_query_and_render_sources_train_one_step_together(tmp_path: Path):
    run_config(
        "queryocc/query_render",
        run_dir=tmp_path,
        overrides=[
            "trainer.max_steps=1",
            "trainer.log_every_n_steps=1",
            "data.batch_size=1",
            "model.supervision.queries.points_per_sample=64",
            "model.supervision.render.rays_per_sample=16",
        ],
    )
    rows = list(csv.DictReader((tmp_path / "logs" / "version_0" / "metrics.csv").open()))
    trained = [r for r in rows if r.get("train/loss")]
    assert trained, rows
    names = {"train/queries/occ", "train/queries/sem", "train/render/depth", "train/render/sem"}
    assert names <= set(rows[0]), sorted(rows[0])
    row = trained[-1]
    total = sum(float(row[n]) for n in names)
    assert math.isfinite(total) and total == pytest.approx(float(row["train/loss"]), rel=1e-4)
