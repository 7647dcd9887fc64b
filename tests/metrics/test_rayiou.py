"""RayIoU: hand-made cases with known answers, and the vectorised metric against a per-ray reference."""

import math

import numpy as np
import pytest
import torch
from metric_batches import SMALL_GRID, make_batch, random_scene

from occplug.geometry import GridSpec
from occplug.metrics import RayIoU
from occplug.metrics.rayiou import (
    cast_query_rays,
    geometry_counts,
    iou_from_counts,
    query_ray_directions,
    rayiou_counts,
    select_origins,
)

# ----------------------------------------------------------------------------------------------
# A per-ray reference, independent of the DDA: every plane crossing of the ray inside the grid,
# sorted; the voxel of each interval is the floor of its midpoint; the depth of a hit is the end
# of the interval of the first occupied voxel (where the ray leaves it, as SparseOcc measures).


def reference_ray(labels, grid, origin, direction, free):
    """``(class, depth)`` of the first occupied voxel along one ray (``(free, inf)`` without)."""
    g = [(origin[a] - grid.lower[a]) / grid.voxel_size[a] for a in range(3)]
    dg = [direction[a] / grid.voxel_size[a] for a in range(3)]
    n = grid.shape
    t_lo, t_hi = 0.0, math.inf
    for a in range(3):
        if dg[a] == 0:
            if not 0 <= g[a] < n[a]:
                return free, math.inf
        else:
            ta, tb = (0 - g[a]) / dg[a], (n[a] - g[a]) / dg[a]
            t_lo, t_hi = max(t_lo, min(ta, tb)), min(t_hi, max(ta, tb))
    if not t_lo < t_hi:
        return free, math.inf
    ts = {t_lo, t_hi}
    for a in range(3):
        if dg[a] != 0:
            ts |= {t for k in range(n[a] + 1) if t_lo < (t := (k - g[a]) / dg[a]) < t_hi}
    ts = sorted(ts)
    for a, b in zip(ts, ts[1:], strict=False):
        mid = 0.5 * (a + b)
        voxel = tuple(math.floor(g[ax] + mid * dg[ax]) for ax in range(3))
        if labels[voxel] != free:
            return labels[voxel], b
    return free, math.inf


def reference_counts(gt, pred, grid, origins, directions, free, num_classes, thresholds):
    gt_l, pred_l = gt.tolist(), pred.tolist()
    gt_count, pred_count = [0] * num_classes, [0] * num_classes
    tp = [[0] * num_classes for _ in thresholds]
    per_ray = []
    for o in origins.tolist():
        for d in directions.tolist():
            gc, gd = reference_ray(np.array(gt_l, dtype=object), grid, o, d, free)
            pc, pd = reference_ray(np.array(pred_l, dtype=object), grid, o, d, free)
            per_ray.append((gc, gd, pc, pd))
            if gc == free:
                continue
            gt_count[gc] += 1
            pred_count[pc] += 1
            for j, tau in enumerate(thresholds):
                tp[j][gc] += int(gc == pc and abs(pd - gd) < tau)
    return per_ray, torch.tensor(gt_count), torch.tensor(pred_count), torch.tensor(tp)


@pytest.mark.parametrize("seed", range(3))
def test_vectorised_equals_per_ray_reference(seed):
    labels, pred, origins = random_scene(seed)
    directions = query_ray_directions()[seed::5]  # 2,808 of the 14,040 directions per origin
    rays = cast_query_rays(pred, labels, SMALL_GRID, origins, free_label=4, directions=directions)
    per_ray, gt_count, pred_count, tp = reference_counts(
        labels, pred, SMALL_GRID, origins, directions, 4, 5, (1.0, 2.0, 4.0)
    )
    assert len(per_ray) >= 2000
    ref = torch.tensor([[r[0], r[2]] for r in per_ray])
    assert torch.equal(rays.gt_class, ref[:, 0]) and torch.equal(rays.pred_class, ref[:, 1])
    ref_depth = torch.tensor([[r[1], r[3]] for r in per_ray], dtype=torch.float64)
    assert torch.allclose(rays.gt_depth, ref_depth[:, 0], atol=1e-9, rtol=0)  # inf == inf included
    assert torch.allclose(rays.pred_depth, ref_depth[:, 1], atol=1e-9, rtol=0)
    counts = rayiou_counts(rays, 5, 4, (1.0, 2.0, 4.0))
    assert torch.equal(counts[0], gt_count) and torch.equal(counts[1], pred_count) and torch.equal(counts[2], tp)
    assert 0 < tp[0].sum() < tp[2].sum() < gt_count.sum()  # not vacuous: all thresholds matter
    # class-agnostic counts: evaluated rays, those the prediction hits, those hit within tau (any classes)
    evaluated = [r for r in per_ray if r[0] != 4]
    hit = [r for r in evaluated if r[2] != 4]
    geo = geometry_counts(rays, 4, (1.0, 2.0, 4.0))
    assert geo[0].item() == len(evaluated) and geo[1].item() == len(hit)
    assert geo[2].tolist() == [sum(abs(r[3] - r[1]) < tau for r in hit) for tau in (1.0, 2.0, 4.0)]
    assert (geo[2] > tp.sum(1)).all()  # some rays hit at the right depth with the wrong class


def test_query_ray_directions_follow_sparseocc():
    d = query_ray_directions()
    assert d.shape == (39 * 360, 3) and d.dtype == torch.float64
    assert torch.allclose(d.norm(dim=-1), torch.ones(len(d), dtype=torch.float64))
    pitch = torch.asin(d[::360, 2])
    assert math.isclose(pitch[0].item(), -math.pi / 4, abs_tol=1e-12)  # k = 0: -(pi/2 - atan(1))
    assert math.isclose(pitch[9].item(), -(math.pi / 2 - math.atan(10)), abs_tol=1e-12)
    assert pitch[-2] < 0.21 <= pitch[-1]  # continued with the last spacing until past 0.21 rad
    assert torch.allclose(pitch[10:].diff(), (pitch[9] - pitch[8]).expand(28))
    assert torch.allclose(
        d[1],
        torch.tensor(
            [
                math.cos(pitch[0]) * math.cos(math.radians(1)),
                math.cos(pitch[0]) * math.sin(math.radians(1)),
                math.sin(pitch[0]),
            ],
            dtype=torch.float64,
        ),
    )


def test_select_origins_filters_then_subsamples_evenly():
    xs = torch.arange(-45.0, 46.0, 5.0)  # 19 positions, 15 of them with |x| < 39
    origins = torch.stack([xs, torch.zeros_like(xs), torch.full_like(xs, 1.8)], -1)
    origins[3, 1] = 39.0  # |y| = 39 is dropped too (strict)
    kept = origins[(xs.abs() < 39) & (origins[:, 1].abs() < 39)]
    chosen = select_origins(origins)
    expected = kept[np.round(np.linspace(0, len(kept) - 1, 8)).astype(int)]
    assert chosen.shape == (8, 3) and torch.equal(chosen, expected.double())
    assert torch.equal(select_origins(origins[:5]), origins[[2, 4]].double())  # fewer than 8: all kept, in order
    assert select_origins(origins[:1]).shape == (0, 3)  # x = -45: nothing left


# ----------------------------------------------------------------------------------------------
# Hand-made cases on a unit grid [0, 10) x [0, 4) x [0, 4), one ray along +x from (0.5, 0.5, 0.5).

LINE = GridSpec((0, 0, 0, 10, 4, 4), 1.0)
FREE = 3
ALONG_X = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
START = torch.tensor([[0.5, 0.5, 0.5]])


def wall(x, cls=1):
    grid = torch.full(LINE.shape, FREE)
    grid[x, 0, 0] = cls
    return grid


def one_ray(pred, gt):
    """Counts and ``(3, K)`` IoU (percent) of the single ray, thresholds 1, 2, 4 m."""
    counts = rayiou_counts(cast_query_rays(pred, gt, LINE, START, FREE, ALONG_X), 4, FREE, (1.0, 2.0, 4.0))
    return counts, iou_from_counts(*counts) * 100


def test_one_voxel_one_ray_depth_is_where_the_ray_leaves_the_voxel():
    rays = cast_query_rays(wall(6), wall(5, cls=2), LINE, START, FREE, ALONG_X)
    assert rays.gt_class.tolist() == [2] and rays.gt_depth.tolist() == [5.5]  # leaves voxel 5 at x = 6
    assert rays.pred_class.tolist() == [1] and rays.pred_depth.tolist() == [6.5]
    inside = cast_query_rays(wall(0), wall(0), LINE, START, FREE, ALONG_X)  # origin inside the voxel
    assert inside.gt_depth.tolist() == [0.5]
    miss = cast_query_rays(torch.full(LINE.shape, FREE), wall(5), LINE, START, FREE, ALONG_X)
    assert miss.pred_class.tolist() == [FREE] and miss.pred_depth.tolist() == [math.inf]


def test_perfect_one_ray_scores_100_and_empty_prediction_scores_0():
    (gt, pred, tp), iou = one_ray(wall(5), wall(5))
    assert gt.tolist() == pred.tolist() == [0, 1, 0, 0] and tp[:, 1].tolist() == [1, 1, 1]
    assert iou[:, 1].tolist() == [100, 100, 100] and iou[:, 0].isnan().all()  # absent from both: NaN, skipped
    (gt, pred, tp), iou = one_ray(torch.full(LINE.shape, FREE), wall(5))
    assert gt.tolist() == [0, 1, 0, 0] and pred.tolist() == [0, 0, 0, 1]  # the ray's prediction: free
    assert iou[:, 1].tolist() == [0, 0, 0]


def test_shift_by_one_voxel_fails_at_1m_and_passes_at_2m_and_4m():
    (_, _, tp), iou = one_ray(wall(6), wall(5))  # depth error exactly 1 m: not < 1
    assert tp[:, 1].tolist() == [0, 1, 1] and iou[:, 1].tolist() == [0, 100, 100]
    _, iou = one_ray(wall(8), wall(5))  # 3 m: only the 4 m threshold passes
    assert iou[:, 1].tolist() == [0, 0, 100]
    (gt, pred, tp), iou = one_ray(wall(5, cls=2), wall(5))  # right depth, wrong class
    assert tp.sum() == 0 and pred.tolist() == [0, 0, 1, 0] and iou[:, 1].tolist() == iou[:, 2].tolist() == [0, 0, 0]


def test_rays_escaping_the_ground_truth_are_not_evaluated():
    (gt, pred, tp), iou = one_ray(wall(5), torch.full(LINE.shape, FREE))  # a wall the ground truth lacks
    assert gt.sum() == pred.sum() == tp.sum() == 0 and iou.isnan().all()


@pytest.mark.filterwarnings("ignore:The ``compute`` method")  # states set by hand, not by update()
def test_metric_means_per_threshold_then_over_thresholds():
    m = RayIoU(num_classes=4, free_label=FREE, grid=LINE)
    m.gt_count += torch.tensor([2, 1, 0, 0])  # hand-set counts: IoU of class 0 1/3, 1, 1; class 1 0, 0, 1
    m.pred_count += torch.tensor([2, 1, 0, 0])
    m.tp += torch.tensor([[1, 0, 0, 0], [2, 0, 0, 0], [2, 1, 0, 0]])
    res = m.compute()
    assert math.isclose(res["RayIoU_1m"].item(), 100 / 6, rel_tol=1e-6)  # mean(1/3, 0); class 2 skipped
    assert math.isclose(res["RayIoU_2m"].item(), 50, rel_tol=1e-6)
    assert math.isclose(res["RayIoU_4m"].item(), 100, rel_tol=1e-6)
    assert math.isclose(res["RayIoU"].item(), (100 / 6 + 50 + 100) / 3, rel_tol=1e-6)
    assert math.isclose(res["RayIoU_class_0"].item(), (100 / 3 + 100 + 100) / 3, rel_tol=1e-6)
    assert math.isnan(res["RayIoU_class_2"].item())


# ----------------------------------------------------------------------------------------------
# The metric on batches.


def test_perfect_empty_and_shifted_predictions_on_a_scene():
    labels, pred, origins = random_scene(7)
    batch = make_batch(labels[None], sequence_lidar_origins=[origins])
    m = RayIoU(num_classes=5, free_label=4, grid=SMALL_GRID)
    m.update(labels[None], batch)
    assert all(v.item() == 100 for k, v in m.compute().items())
    m.reset()
    m.update(torch.full_like(labels, 4)[None], batch)
    assert m.compute()["RayIoU"].item() == 0
    m.reset()
    m.update(torch.roll(labels, 1, 0)[None], batch)
    res = m.compute()
    assert 0 < res["RayIoU_1m"] < res["RayIoU_2m"] <= res["RayIoU_4m"] < 100


def test_prediction_ids_outside_the_taxonomy_are_occupied_with_no_class():
    """As SparseOcc scores them (e.g. every car voxel set to 255): the ray stops there, so geometry is
    untouched, but it counts for no class; occ3d_miou keeps refusing such ids."""
    from occplug.metrics import Occ3DMIoU

    labels, _, origins = random_scene(7)
    batch = make_batch(labels[None], sequence_lidar_origins=[origins])
    perfect = RayIoU(num_classes=5, free_label=4, grid=SMALL_GRID)
    perfect.update(labels[None], batch)
    for unknown in (255, -3, 5):
        pred = torch.where(labels == 1, unknown, labels)
        m = RayIoU(num_classes=5, free_label=4, grid=SMALL_GRID)
        m.update(pred[None], batch)
        assert int(perfect.gt_count[1]) > 0 and torch.equal(m.gt_count, perfect.gt_count)
        assert int(m.pred_count[1]) == 0 and (m.tp[:, 1] == 0).all()
        others = [0, 2, 3]
        assert torch.equal(m.tp[:, others], perfect.tp[:, others])
        assert torch.equal(m.pred_count[others], perfect.pred_count[others])
        res = m.compute()
        assert res["RayIoU_class_1"].item() == 0 and res["RayIoU_geometry"].item() == 100
        present = [c for c in range(4) if int(perfect.gt_count[c]) > 0]
        assert res["RayIoU"].item() == pytest.approx(100 * (len(present) - 1) / len(present))
    with pytest.raises(ValueError, match="class id 255, outside 0..4"):
        Occ3DMIoU(num_classes=5, free_label=4, mask="none").update(torch.where(labels == 1, 255, labels)[None], batch)


def test_the_compiled_and_the_pure_pytorch_walks_give_the_same_counts():
    pytest.importorskip("numba")
    labels, pred, origins = random_scene(5)
    batch = make_batch(labels[None], sequence_lidar_origins=[origins])
    states = []
    for kernel in ("torch", "numba", "auto"):
        m = RayIoU(num_classes=5, free_label=4, grid=SMALL_GRID, kernel=kernel)
        m.update(pred[None], batch)
        states.append([m.gt_count, m.pred_count, m.tp, m.geo_tp, m.geo_pred_count])
    assert int(states[0][0].sum()) > 0
    for other in states[1:]:
        assert all(torch.equal(a, b) for a, b in zip(states[0], other, strict=True))


def test_non_finite_origins_are_refused():
    labels, _, origins = random_scene(1)
    for bad in (math.nan, math.inf):
        broken = origins.clone()
        broken[-1, 1] = bad
        with pytest.raises(ValueError, match="non-finite LiDAR origins"):
            RayIoU(num_classes=5, free_label=4, grid=SMALL_GRID).update(
                labels[None], make_batch(labels[None], sequence_lidar_origins=[broken])
            )


def test_origins_fall_back_to_the_lidar_then_the_ego_origin():
    labels, pred, _ = random_scene(3)
    lidar = torch.eye(4)
    lidar[:3, 3] = torch.tensor([0.5, -0.25, 0.75])
    expected = RayIoU(num_classes=5, free_label=4, grid=SMALL_GRID)
    expected.update(pred[None], make_batch(labels[None], sequence_lidar_origins=[lidar[:3, 3][None]]))
    fallback = RayIoU(num_classes=5, free_label=4, grid=SMALL_GRID)
    fallback.update(pred[None], make_batch(labels[None], lidar_to_ego=lidar[None]))
    assert torch.equal(fallback.tp, expected.tp) and torch.equal(fallback.gt_count, expected.gt_count)
    at_ego = RayIoU(num_classes=5, free_label=4, grid=SMALL_GRID)
    at_ego.update(pred[None], make_batch(labels[None], sequence_lidar_origins=[torch.zeros(1, 3)]))
    bare = RayIoU(num_classes=5, free_label=4, grid=SMALL_GRID)
    bare.update(pred[None], make_batch(labels[None]))
    assert torch.equal(bare.tp, at_ego.tp) and not torch.equal(bare.gt_count, expected.gt_count)


def test_grid_is_required_off_occ3d_and_the_table_names_the_settings():
    labels, _, origins = random_scene(0)
    with pytest.raises(ValueError, match="rayiou needs the evaluation grid"):
        RayIoU(num_classes=5, free_label=4).update(labels[None], make_batch(labels[None]))
    m = RayIoU(num_classes=5, class_names=list("abcdf"), free_label=4, grid=SMALL_GRID)
    m.update(labels[None], make_batch(labels[None], sequence_lidar_origins=[origins]))
    table = m.table()
    assert table.splitlines()[0].startswith("RayIoU (SparseOcc / Occ3D-nuScenes leaderboard; thresholds 1, 2, 4 m;")
    assert "grid 16x16x6 @ 0.5/0.5/0.5 m" in table and "|x|,|y| < 39 m" in table
    n = len(select_origins(origins, 39.0, 8))
    assert table.splitlines()[1].startswith(f"cast from {n:.2f} origins per sample on average over 1 samples")
    assert [line.split()[0] for line in table.splitlines()[3:7]] == list("abcd")
    one = RayIoU(num_classes=5, free_label=4, grid=SMALL_GRID)
    one.update(labels[None], make_batch(labels[None], sequence_lidar_origins=[origins[:1]]))
    assert "one origin per sample: not comparable with leaderboard RayIoU" in one.table()
    # no dynamic / static groups for an unknown taxonomy, no _excl keys without exclude_classes
    assert set(m.compute()) == {
        "RayIoU",
        "RayIoU_1m",
        "RayIoU_2m",
        "RayIoU_4m",
        "RayIoU_geometry",
        *(f"RayIoU_{c}" for c in "abcd"),
    }
    assert "RayIoU geometry" in table and "RayIoU dynamic" not in table and "excl." not in table


# ----------------------------------------------------------------------------------------------
# Beyond the reference: class-agnostic (geometry), dynamic / static and excluded-class summaries.


def test_geometry_counts_of_hand_made_rays():
    """Three rays from (0.5, 0.5, 0.5) on the unit grid: +x, +y and +z."""
    directions = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    gt = torch.full(LINE.shape, FREE)
    gt[5, 0, 0] = 1  # +x: class 1, leaves at x = 6 (depth 5.5)
    gt[0, 3, 0] = 2  # +y: class 2, leaves at y = 4 (depth 3.5); +z: free, not evaluated
    pred = torch.full(LINE.shape, FREE)
    pred[5, 0, 0] = 2  # +x: right depth, wrong class
    pred[0, 2, 0] = 2  # +y: right class, 1 m short (depth 2.5)
    pred[0, 0, 2] = 1  # +z: a hit where the ground truth has none: not evaluated
    rays = cast_query_rays(pred, gt, LINE, START, FREE, directions)
    n_gt, n_pred, tp = geometry_counts(rays, FREE, (1.0, 2.0, 4.0))
    assert (n_gt.item(), n_pred.item(), tp.tolist()) == (2, 2, [1, 2, 2])
    geometry = iou_from_counts(n_gt, n_pred, tp)  # TP / (2 + 2 - TP): 1/3, 1, 1
    assert torch.allclose(geometry, torch.tensor([1 / 3, 1.0, 1.0], dtype=torch.float64))
    # semantic: class 1 never predicted (0); class 2: N_gt 1, N_pred 2, TP 0, 1, 1 -> 0, 1/2, 1/2
    iou = iou_from_counts(*rayiou_counts(rays, 4, FREE, (1.0, 2.0, 4.0)))
    assert iou[:, 1].tolist() == [0, 0, 0] and iou[:, 2].tolist() == [0, 0.5, 0.5]
    m = RayIoU(num_classes=4, free_label=FREE, grid=LINE)  # the metric's summaries of the same counts
    m.geo_gt_count += n_gt
    m.geo_pred_count += n_pred
    m.geo_tp += tp
    semantic = rayiou_counts(rays, 4, FREE, (1.0, 2.0, 4.0))
    m.gt_count += semantic[0]
    m.pred_count += semantic[1]
    m.tp += semantic[2]
    with pytest.warns(UserWarning, match="The ``compute`` method"):  # states set by hand, not by update()
        res = m.compute()
    assert math.isclose(res["RayIoU_geometry"].item(), 100 * (1 / 3 + 1 + 1) / 3, rel_tol=1e-6)
    assert math.isclose(res["RayIoU"].item(), 100 * (0 + 0 + 0 + 0 + 0.5 + 0.5) / 6, rel_tol=1e-6)


def test_right_depths_with_wrong_classes_score_100_in_geometry_only():
    labels, _, origins = random_scene(5)
    relabelled = torch.where(labels == 4, 4, (labels + 1) % 4)  # every occupied voxel another class
    batch = make_batch(labels[None], sequence_lidar_origins=[origins])
    m = RayIoU(num_classes=5, free_label=4, grid=SMALL_GRID)
    m.update(relabelled[None], batch)
    res = m.compute()
    assert res["RayIoU_geometry"].item() == 100 and m.geo_gt_count == m.gt_count.sum() > 0
    assert res["RayIoU"].item() == 0  # no ray has its class right
    m.reset()
    m.update(torch.full_like(labels, 4)[None], batch)  # nothing predicted
    assert m.compute()["RayIoU_geometry"].item() == 0
    m.reset()
    m.update(torch.roll(labels, 1, 0)[None], batch)  # shifted: geometry at least as good as the classes
    res = m.compute()
    assert res["RayIoU"] <= res["RayIoU_geometry"] < 100
    iou = iou_from_counts(m.geo_gt_count, m.geo_pred_count, m.geo_tp)
    assert math.isclose(res["RayIoU_geometry"].item(), iou.mean().item() * 100, rel_tol=1e-6)


@pytest.mark.filterwarnings("ignore:The ``compute`` method")  # states set by hand, not by update()
def test_dynamic_static_and_excluded_means_by_hand():
    from occplug.data.classes import OCC3D_CLASSES

    m = RayIoU(class_names=OCC3D_CLASSES, exclude_classes=["traffic_cone", "others"])
    ids = {name: OCC3D_CLASSES.index(name) for name in OCC3D_CLASSES}
    # (N_gt, N_pred, TP at 1, 2, 4 m) of the classes present; every other class is absent (NaN, skipped)
    counts = {
        "others": (2, 0, (0, 0, 0)),  # 0, 0, 0
        "car": (4, 4, (2, 4, 4)),  # 1/3, 1, 1 -> 7/9
        "pedestrian": (1, 1, (1, 1, 1)),  # 1
        "traffic_cone": (1, 3, (0, 0, 1)),  # 0, 0, 1/3 -> 1/9
        "driveable_surface": (6, 3, (3, 3, 3)),  # 1/2
        "vegetation": (2, 2, (0, 1, 2)),  # 0, 1/3, 1 -> 4/9
    }
    for name, (n_gt, n_pred, tp) in counts.items():
        m.gt_count[ids[name]] = n_gt
        m.pred_count[ids[name]] = n_pred
        m.tp[:, ids[name]] = torch.tensor(tp)
    per_class = {"others": 0, "car": 7 / 9, "pedestrian": 1, "traffic_cone": 1 / 9, "driveable_surface": 1 / 2,
                 "vegetation": 4 / 9}  # fmt: skip
    res = m.compute()
    for name, value in per_class.items():
        assert math.isclose(res[f"RayIoU_{name}"].item(), 100 * value, rel_tol=1e-6, abs_tol=1e-6)
    assert math.isnan(res["RayIoU_bus"].item())
    assert math.isclose(res["RayIoU"].item(), 100 * sum(per_class.values()) / 6, rel_tol=1e-6)
    # dynamic (Occ3D's ten object classes): car, pedestrian, traffic_cone present; static: driveable, vegetation
    assert math.isclose(res["RayIoU_dynamic"].item(), 100 * (7 / 9 + 1 + 1 / 9) / 3, rel_tol=1e-6)
    assert math.isclose(res["RayIoU_static"].item(), 100 * (1 / 2 + 4 / 9) / 2, rel_tol=1e-6)
    # without traffic_cone and others
    assert math.isclose(res["RayIoU_excl"].item(), 100 * (7 / 9 + 1 + 1 / 2 + 4 / 9) / 4, rel_tol=1e-6)
    assert math.isclose(res["RayIoU_dynamic_excl"].item(), 100 * (7 / 9 + 1) / 2, rel_tol=1e-6)
    assert math.isclose(res["RayIoU_static_excl"].item(), res["RayIoU_static"].item(), rel_tol=1e-6)
    table = m.table()
    for line in ("RayIoU dynamic", "RayIoU static", "RayIoU geometry", "without others, traffic_cone:",
                 "RayIoU excl.", "RayIoU dynamic excl.", "RayIoU static excl."):  # fmt: skip
        assert line in table
    assert f"{'RayIoU dynamic':<24}{res['RayIoU_dynamic'].item():>9.2f}" in table


def test_groups_follow_the_taxonomy_or_the_arguments_and_match_the_per_class_keys():
    labels, pred, origins = random_scene(2)
    batch = make_batch(labels[None], sequence_lidar_origins=[origins])
    names = ["a", "b", "c", "d", "free"]
    m = RayIoU(num_classes=5, class_names=names, free_label=4, grid=SMALL_GRID, dynamic_classes=["a", "b"],
               static_classes=["c"], exclude_classes=["b"])  # fmt: skip
    m.update(pred[None], batch)
    res = m.compute()
    per_class = {n: res[f"RayIoU_{n}"].item() for n in "abcd"}
    assert all(0 < v < 100 for v in per_class.values())
    assert math.isclose(res["RayIoU_dynamic"].item(), (per_class["a"] + per_class["b"]) / 2, rel_tol=1e-5)
    assert math.isclose(res["RayIoU_static"].item(), per_class["c"], rel_tol=1e-5)
    assert math.isclose(res["RayIoU_excl"].item(), (per_class["a"] + per_class["c"] + per_class["d"]) / 3, rel_tol=1e-5)
    assert math.isclose(res["RayIoU_dynamic_excl"].item(), per_class["a"], rel_tol=1e-5)
    assert math.isclose(res["RayIoU_static_excl"].item(), per_class["c"], rel_tol=1e-5)
    plain = RayIoU(num_classes=5, class_names=names, free_label=4, grid=SMALL_GRID)
    plain.update(pred[None], batch)
    assert not any(k.endswith(("_dynamic", "_static", "_excl")) for k in plain.compute())


def test_bad_group_exclude_and_class_names_are_clear_errors():
    names = ["a", "b", "c", "free"]
    with pytest.raises(ValueError, match=r"rayiou.exclude_classes: unknown class 'x' \(semantic classes: a, b, c\)"):
        RayIoU(num_classes=4, class_names=names, free_label=3, exclude_classes=["a", "x"])
    with pytest.raises(ValueError, match="rayiou.exclude_classes: unknown class 'free'"):
        RayIoU(num_classes=4, class_names=names, free_label=3, exclude_classes=["free"])
    with pytest.raises(ValueError, match="rayiou.static_classes: unknown class 'y'"):
        RayIoU(num_classes=4, class_names=names, free_label=3, dynamic_classes=["a"], static_classes=["y"])
    with pytest.raises(ValueError, match="rayiou: give both dynamic_classes and static_classes, or neither"):
        RayIoU(num_classes=4, class_names=names, free_label=3, dynamic_classes=["a"])
    with pytest.raises(ValueError, match="rayiou: class 'geometry' would share its key RayIoU_geometry"):
        RayIoU(num_classes=3, class_names=["geometry", "b", "free"], free_label=2)
