"""Free space along rays that end at no surface (issue 40): the sky pixels' rays, the query and render sources'
use of them, the synthetic mapping that marks them, and the diagnosis script's tallies on a hand-made case."""

from __future__ import annotations

import pytest
import torch

from occplug.data import LabelledPoints, free_pixel_rays
from occplug.geometry import GridSpec, camera_rays
from occplug.testing import hand_batch, make_tiny_batch
from occplug_queryocc import QuerySupervision, RenderSupervision
from occplug_queryocc.supervision import sample_sky_negatives, sample_surface_negatives
from occplug_queryocc.tools.diagnose import (
    NO_HIT,
    Tally,
    covered,
    first_hit_classes,
    first_hits_from_camera,
    height_above_ground,
    main,
    seeing_camera,
)

FREE = 17


def _camera_batch(labels):
    """One camera 1.5 m above the ego origin looking along +x (camera z -> ego x, camera x -> -ego y, camera y ->
    -ego z), pixel (u, v) at focal 2 on a 4 x 4 image, with 2D pseudo semantics ``labels`` ``(4, 4)``."""
    k = torch.tensor([[2.0, 0.0, 2.0], [0.0, 2.0, 2.0], [0.0, 0.0, 1.0]])
    pose = torch.eye(4)
    pose[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    pose[:3, 3] = torch.tensor([0.0, 0.0, 1.5])
    return hand_batch(
        1,
        image_hw=(4, 4),
        intrinsics=k.expand(1, 1, 3, 3),
        cam_to_ego=pose.expand(1, 1, 4, 4),
        pseudo_semantics=labels.reshape(1, 1, 4, 4),
        pseudo_depth=torch.zeros(1, 1, 4, 4),
    )


def test_free_pixel_rays_are_the_camera_rays_of_the_free_pixels():
    labels = torch.full((4, 4), 255, dtype=torch.int64)
    labels[0, :] = FREE  # the top row sees the sky
    labels[1, 2] = FREE
    batch = _camera_batch(labels)
    (rays,) = free_pixel_rays(batch, FREE)
    assert len(rays) == 5 and bool((rays.labels == FREE).all())
    origins, dirs, _ = camera_rays(batch.intrinsics[0], batch.cam_to_ego[0], 4, 4)
    expected = dirs[0][labels == FREE]  # (5, 3) in row-major pixel order, as returned
    assert torch.allclose(rays.points - rays.origins, expected, atol=1e-6)
    assert torch.allclose(rays.origins, origins[0].expand(5, 3))
    assert bool((expected[:4, 2] > 0).all())  # the top row looks up
    (every_other,) = free_pixel_rays(batch, FREE, stride=2)  # pixels (0, 0) and (0, 2) of the top row
    assert len(every_other) == 2


def test_sky_negatives_lie_on_their_rays_below_the_grid_top_and_within_far():
    origin = torch.tensor([[0.0, 0.0, 1.5]])
    up = torch.nn.functional.normalize(torch.tensor([[1.0, 0.0, 0.5]]), dim=-1)  # leaves z = 5.4 at 3.9 / 0.447 m
    flat = torch.tensor([[0.0, 1.0, 0.0]])  # never leaves the height range: stops at far
    rays = LabelledPoints(torch.cat([origin + up, origin + flat]), origin.expand(2, 3), torch.full((2,), FREE))
    empty = LabelledPoints(torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0, dtype=torch.int64))
    torch.manual_seed(0)
    q = sample_sky_negatives(
        [(rays, torch.tensor([0.0, -0.5])), (empty, torch.zeros(0))], 400, 5, 30.0, (-1.0, 5.4), 255
    )
    assert q.points.shape == (2, 2000, 3) and not bool(q.occupied.any()) and bool((q.labels == 255).all())
    assert bool(q.valid[0].all()) and not bool(q.valid[1].any())
    pts = q.points[0] - origin
    along = pts.norm(dim=-1)
    on_up = torch.allclose(torch.nn.functional.normalize(pts, dim=-1), up.expand_as(pts), atol=1e-5)
    on_flat = (pts[:, [0, 2]].abs() < 1e-5).all(-1)
    going_up = (pts @ up[0]) > along - 1e-4
    assert bool((going_up | on_flat).all()) and not on_up  # both rays were drawn
    assert float(along[going_up].max()) <= 3.9 / float(up[0, 2]) + 1e-4  # stops at the grid's top
    assert float(along[going_up].max()) > 0.9 * 3.9 / float(up[0, 2])  # ... and reaches near it
    assert float(along[on_flat].max()) <= 30.0 and float(along[on_flat].max()) > 27.0
    assert bool((q.times[0][on_flat] == -0.5).all()) and bool((q.times[0][going_up] == 0.0).all())


def test_query_supervision_adds_sky_negatives_after_its_own_queries_and_off_draws_as_before():
    batch = make_tiny_batch(2, pseudo_labels={"preset": "default", "sky_as_free": True})
    assert bool((batch.pseudo_semantics == FREE).any())  # the tiny world's cameras see sky
    grid = GridSpec((-16.0, -16.0, -1.0, 16.0, 16.0, 5.4), 0.8)
    off = QuerySupervision(points_per_sample=64, grid=grid)
    on = QuerySupervision(points_per_sample=64, sky_rays=32, sky_negatives=3, grid=grid)
    torch.manual_seed(3)
    a = off.queries(batch)
    torch.manual_seed(3)
    b = on.queries(batch)
    n = 64 * 8
    assert a.points.shape[1] == n and b.points.shape[1] == n + 32 * 3
    assert torch.equal(a.points, b.points[:, :n])  # the point queries are drawn first, unchanged
    sky = b.points[:, n:]
    assert not bool(b.occupied[:, n:].any()) and bool(b.valid[:, n:].all())
    assert float(sky[..., 2].max()) <= 5.4 + 1e-4
    # each sky query lies on a ray through a pixel labelled free (above the camera's horizon mostly)
    assert float(sky[..., 2].mean()) > float(batch.cam_to_ego[:, :, 2, 3].mean())


def test_sky_rays_need_a_free_label():
    with pytest.raises(ValueError, match="free_label"):
        QuerySupervision(sky_rays=4, free_label=None)
    with pytest.raises(ValueError, match="free_label"):
        RenderSupervision(sky_rays=4, free_label=None)


def test_render_sky_rays_follow_the_depth_rays_and_render_against_far():
    batch = make_tiny_batch(2, pseudo_labels={"preset": "default", "sky_as_free": True})
    off = RenderSupervision(rays_per_sample=16, samples_per_ray=8)
    on = RenderSupervision(rays_per_sample=16, samples_per_ray=8, sky_rays=6)
    torch.manual_seed(5)
    a = off.rays(batch)
    torch.manual_seed(5)
    b = on.rays(batch)
    assert b.points.shape[1] == 22 and torch.equal(a.points[0], b.points[0, :16])  # sample 0 draws its sky last
    assert bool((b.labels[:, 16:] == FREE).all()) and bool(torch.isinf(b.target_depth[:, 16:]).all())
    # a field that is empty everywhere renders every sky ray at far: zero depth loss on them
    from occplug.interfaces import ModelOutputs, QueryResult

    def empty(name, points, times=None):
        return QueryResult(
            class_logits=torch.zeros(*points.shape[:2], 18), occupancy_logit=torch.full(points.shape[:2], -30.0)
        )

    only_sky = RenderSupervision(rays_per_sample=1, samples_per_ray=8, sky_rays=6, max_depth=1e-3)  # no depth pixel
    losses = only_sky(batch, ModelOutputs(None, None, None, {}, empty))
    assert float(losses["depth"]) == pytest.approx(0.0, abs=1e-5)


def test_the_synthetic_mapping_marks_sky_free_only_when_asked():
    plain = make_tiny_batch(1, pseudo_labels="default")
    marked = make_tiny_batch(1, pseudo_labels={"preset": "default", "sky_as_free": True})
    assert not bool((plain.pseudo_semantics == FREE).any())
    sky = marked.pseudo_semantics == FREE
    assert bool(sky.any())
    assert torch.equal(plain.pseudo_semantics[~sky], marked.pseudo_semantics[~sky])  # nothing else changes
    assert bool((plain.pseudo_semantics[sky] == 255).all())
    assert (
        float((plain.pseudo_depth[sky] == 0).float().mean()) > 0.9
    )  # sky has no depth (1-pixel boundary errors aside)


# ---------------------------------------------------------------- the diagnosis, on a hand-made field
GRID = GridSpec((0.0, -2.0, 0.0, 8.0, 2.0, 4.0), 1.0)  # 8 x 4 x 4 voxels of 1 m


def _field():
    labels = torch.full(GRID.shape, FREE, dtype=torch.int64)
    labels[:, :, 0] = 11  # road: ground top at z = 1
    labels[6, 1:3, 1:3] = 15  # a 2 m wall at x = 6..7 in the middle two columns
    return labels


def test_height_above_ground_uses_each_columns_ground_top():
    h = height_above_ground(_field(), GRID)
    assert torch.allclose(h[0, 0], torch.tensor([-0.5, 0.5, 1.5, 2.5]))
    labels = _field()
    labels[3, 0, 0] = FREE  # a column without ground takes the median ground top (z = 1)
    assert torch.allclose(height_above_ground(labels, GRID)[3, 0], torch.tensor([-0.5, 0.5, 1.5, 2.5]))


def test_covered_reaches_one_voxel_around_each_point():
    near = covered(torch.tensor([[3.5, 0.5, 1.5], [100.0, 0.0, 0.0]]), GRID)  # the second lies outside
    assert int(near.sum()) == 27
    assert bool(near[2:5, 1:4, 0:3].all())


def test_first_hit_classes_find_the_wall_or_the_sky():
    cam = torch.eye(4)
    cam[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # looks along +x
    cam[:3, 3] = torch.tensor([0.1, 0.0, 1.5])
    voxels = torch.tensor([[3, 2, 1], [5, 2, 3]])  # in front of the wall at its height; above it
    assert first_hit_classes(_field(), GRID, FREE, cam[None], voxels) == [15, NO_HIT]
    # the wall is voxel (6, 2, 1): 3 voxels from (3, 2, 1), 1 from (5, 2, 1); behind (7, 2, 1) the ray meets it first
    voxels = torch.tensor([[3, 2, 1], [5, 2, 1], [7, 2, 1], [5, 2, 3]])
    classes, gaps = first_hits_from_camera(_field(), GRID, FREE, cam[None], voxels)
    assert classes == [15, 15, 15, NO_HIT] and gaps == [3, 1, 0, None]


def test_the_tally_gives_the_known_shares():
    labels = _field()
    pred = labels.clone()
    wrong = [(3, 2, 1), (1, 0, 2), (5, 2, 3), (7, 3, 3)]  # four free voxels predicted occupied
    for i, j, k in wrong:
        pred[i, j, k] = 15
    mask = torch.ones(GRID.shape, dtype=torch.bool)
    mask[7, 3, 3] = False  # not scored
    cam = torch.eye(4)
    cam[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    cam[:3, 3] = torch.tensor([0.1, 0.0, 1.5])
    negatives = torch.tensor([[3.5, 0.5, 1.5]])  # within one voxel of (3, 2, 1) only
    positives = torch.tensor([[5.5, 0.5, 3.5]])  # in voxel (5, 2, 3): within one voxel of it only
    tally = Tally()
    tally.add(pred, labels, mask, GRID, FREE, cam[None], negatives, positives, [str(c) for c in range(18)])
    scored_free = int((mask & (labels == FREE)).sum())
    shares = tally.shares()
    assert shares["false_occupied_voxels"] == 3 and shares["scored_free_voxels"] == scored_free
    assert shares["by_height_above_ground_pct"] == {
        "< 1 m": pytest.approx(100 / 3, abs=0.01),
        "1-2 m": pytest.approx(100 / 3, abs=0.01),
        "2-4 m": pytest.approx(100 / 3, abs=0.01),
        ">= 4 m": 0.0,
    }
    assert shares["no_query_within_one_voxel_pct"] == pytest.approx(100 / 3, abs=0.01)  # (1, 0, 2)
    assert shares["no_negative_within_one_voxel_pct"] == pytest.approx(200 / 3, abs=0.01)
    assert shares["no_positive_within_one_voxel_pct"] == pytest.approx(200 / 3, abs=0.01)
    # (3, 2, 1) sees the wall behind it; (1, 0, 2) looks past it, (5, 2, 3) over it (the wall's top is z = 3)
    assert shares["by_first_hit_pct"] == {
        NO_HIT: pytest.approx(200 / 3, abs=0.01),
        "15": pytest.approx(100 / 3, abs=0.01),
    }
    assert shares["by_voxels_to_first_hit_pct"] == {
        "1": 0.0,
        "2": 0.0,
        "3-4": pytest.approx(100 / 3, abs=0.01),  # (3, 2, 1): the wall's voxel (6, 2, 1) is 3 away
        ">= 5": 0.0,
        "hit before it": 0.0,
        NO_HIT: pytest.approx(200 / 3, abs=0.01),
    }
    assert shares["by_distance_pct"] == {"< 8 m": 100.0, "8-16 m": 0.0, "16-24 m": 0.0, ">= 24 m": 0.0}
    # the other side: the road (8 x 4 scored voxels) all predicted; the wall's 4 voxels predicted too
    assert shares["scored_occupied_voxels"] == 36 and shares["false_free_voxels"] == 0
    pred[6, 1, 1] = FREE  # miss one wall voxel
    tally = Tally()
    tally.add(pred, labels, mask, GRID, FREE, cam[None], negatives, positives, [str(c) for c in range(18)])
    assert tally.shares()["false_free_pct_by_class"] == {"11": 0.0, "15": 25.0}


def test_surface_negatives_lie_on_the_seen_segment_within_zeta_in_front_of_the_point():
    origin = torch.tensor([[0.0, 0.0, 1.5], [0.0, 0.0, 1.5]])
    points = torch.tensor([[10.0, 0.0, 1.5], [0.0, 0.3, 1.5]])  # the second is nearer than zeta
    sets = [(LabelledPoints(points, origin, torch.tensor([15, 11])), torch.zeros(2))]
    torch.manual_seed(0)
    q = sample_surface_negatives(sets, 200, 3, 0.5, 255)
    assert q.points.shape == (1, 600, 3) and not bool(q.occupied.any()) and bool(q.valid.all())
    on_x = q.points[0, :, 1].abs() < 1e-6  # on the first ray
    assert bool(((q.points[0, on_x, 0] >= 9.5 - 1e-5) & (q.points[0, on_x, 0] <= 10.0)).all())
    on_y = ~on_x
    assert bool(((q.points[0, on_y, 1] >= -1e-6) & (q.points[0, on_y, 1] <= 0.3)).all())  # never behind the sensor
    assert bool(on_x.any()) and bool(on_y.any())


def test_surface_negatives_are_drawn_after_the_point_queries():
    batch = make_tiny_batch(2, pseudo_labels="default")
    torch.manual_seed(1)
    a = QuerySupervision(points_per_sample=32).queries(batch)
    torch.manual_seed(1)
    b = QuerySupervision(points_per_sample=32, surface_negatives=2).queries(batch)
    assert b.points.shape[1] == 32 * 8 + 32 * 2 and torch.equal(a.points, b.points[:, : 32 * 8])
    assert not bool(b.occupied[:, 32 * 8 :].any())


def test_the_diagnosis_names_a_bad_input_in_one_line_and_exits_2(tmp_path, capsys):
    assert main([str(tmp_path / "missing.ckpt")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "missing.ckpt" in err and "Traceback" not in err
    (tmp_path / "junk.ckpt").write_bytes(b"not a checkpoint")
    assert main([str(tmp_path / "junk.ckpt")]) == 2
    assert "junk.ckpt" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main([str(tmp_path / "junk.ckpt"), "--draws", "0"])
    assert exc.value.code == 2


def test_the_tally_splits_false_occupied_voxels_by_the_camera_that_sees_them():
    labels = _field()
    pred = labels.clone()
    for i, j, k in [(1, 0, 2), (5, 0, 2), (7, 0, 3)]:  # one free voxel behind the rig, two in front of it
        pred[i, j, k] = 15
    front = torch.eye(4)
    front[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # optical axis +x
    front[:3, 3] = torch.tensor([4.0, 0.0, 1.5])
    back = front.clone()
    back[:3, :3] = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # optical axis -x
    cams = torch.stack([front, back])
    voxels = torch.tensor([[1, 0, 2], [5, 0, 2], [3, 3, 3], [4, 1, 1]])
    assert seeing_camera(GRID, cams, voxels).tolist() == [1, 0, 1, 0]  # centres at x < 4: the back camera
    mask = torch.ones(GRID.shape, dtype=torch.bool)
    tally = Tally()
    none = torch.zeros(0, 3)
    tally.add(pred, labels, mask, GRID, FREE, cams, none, none, [str(c) for c in range(18)], ("FRONT", "BACK"))
    shares = tally.shares()
    free = labels == FREE
    n_back, n_front = int(free[:4].sum()), int(free[4:].sum())  # voxel x index < 4: centre x < 4
    assert shares["by_camera_pct"] == {
        "FRONT": pytest.approx(200 / 3, abs=0.01),
        "BACK": pytest.approx(100 / 3, abs=0.01),
    }
    assert shares["false_occupied_pct_of_scored_free_by_camera"] == {
        "FRONT": pytest.approx(round(200 / n_front, 2)),
        "BACK": pytest.approx(round(100 / n_back, 2)),
    }
