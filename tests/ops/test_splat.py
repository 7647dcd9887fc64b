"""The fast splat (occplug.ops.splat) against the naive reference, its geometry cache, and the public
FrustumSplatter (per-point path, BEV, per-camera depths, point -> cell hook, contracted grids).

Random geometry: cameras at random positions/yaws/pitches with random focal lengths, images
augmented by a random resize + crop (+ horizontal flip), on a grid that some frustum points miss.
"""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

from occplug.components import LSSViewTransform, splat
from occplug.data.frame import Batch
from occplug.geometry import GridSpec, make_pose
from occplug.ops import (
    FrustumSplatter,
    SplatPlanCache,
    build_splat_plan,
    frustum_points,
    geometry_key,
    splat_outer,
    splat_points,
)
from occplug.testing import hand_batch

H, W, S = 32, 64, 8  # images; stride -> 4 x 8 feature cells
GRID = GridSpec(range=(-12.0, -12.0, -1.0, 12.0, 12.0, 4.6), voxel_size=0.8)
CAM_AXES = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # OpenCV camera in a +x-facing ego


def _rot(yaw: float, pitch: float) -> Tensor:
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    rz = torch.tensor([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = torch.tensor([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    return rz @ ry @ CAM_AXES


def random_batch(b: int, n: int, seed: int, augment: bool = True) -> Batch:
    """``b`` samples of ``n`` cameras each, every camera and augmentation drawn at random."""
    g = torch.Generator().manual_seed(seed)

    def u(lo: float, hi: float) -> float:
        return lo + (hi - lo) * float(torch.rand((), generator=g))

    ks, poses, augs = [], [], []
    for _ in range(b * n):
        f = u(25.0, 60.0)
        ks.append(torch.tensor([[f, 0.0, u(28.0, 36.0)], [0.0, f * u(0.95, 1.05), u(12.0, 20.0)], [0.0, 0.0, 1.0]]))
        poses.append(
            make_pose(_rot(u(-math.pi, math.pi), u(-0.2, 0.2)), torch.tensor([u(-2, 2), u(-1, 1), u(1.2, 1.9)]))
        )
        aug = torch.eye(3)
        if augment:  # resize by s about the pixel-centre convention, crop by (tx, ty), maybe flip
            s = u(0.6, 1.3)
            aug = torch.tensor(
                [[s, 0.0, 0.5 * s - 0.5 - u(-6, 6)], [0.0, s, 0.5 * s - 0.5 - u(-4, 4)], [0.0, 0.0, 1.0]]
            )
            if u(0, 1) < 0.5:
                aug = torch.tensor([[-1.0, 0.0, W - 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) @ aug
        augs.append(aug)
    return hand_batch(
        b,
        images=torch.zeros(b, n, 3, H, W),
        intrinsics=torch.stack(ks).view(b, n, 3, 3),
        cam_to_ego=torch.stack(poses).view(b, n, 4, 4),
        img_aug=torch.stack(augs).view(b, n, 3, 3),
    )


def make_lss(splat_impl: str, channels: int = 5, seed: int = 0) -> LSSViewTransform:
    torch.manual_seed(seed)
    return LSSViewTransform(
        in_channels=4,
        image_stride=S,
        grid=GRID,
        out_channels=channels,
        depth_bins=[1.0, 21.0, 1.0],
        hidden=8,
        splat=splat_impl,
    )


def naive_outer(depth: Tensor, context: Tensor, index: Tensor, v: int) -> Tensor:
    """The reference: (B, N, D, h, w) x (B, N, C, h, w) products splatted with a (B, N, D, h, w) local index -> (B, C, V)."""
    b, n, d, h, w = depth.shape
    c = context.shape[2]
    frustum = (depth.view(b, n, d, 1, h, w) * context.view(b, n, 1, c, h, w)).permute(0, 1, 2, 4, 5, 3).reshape(-1, c)
    offset = torch.arange(b).view(b, 1, 1, 1, 1) * v
    flat = torch.where(index >= 0, index + offset, index).reshape(-1)
    return splat(frustum, flat, b * v).view(b, v, c).permute(0, 2, 1)


# ----------------------------------------------------------------------------- the plan
def test_plan_structure_on_a_hand_made_index() -> None:
    # N=1, D=3, h=1, w=2: cells 0 and 1; V = 4 voxels.
    index = torch.tensor([[[[2, 0]], [[2, -1]], [[3, 0]]]])  # (1, 3, 1, 2)
    plan = build_splat_plan(index, 4)
    assert plan.voxels.tolist() == [0, 2, 3]  # voxel 1 stays empty
    assert plan.crow.tolist() == [0, 1, 2, 3] and plan.col.tolist() == [1, 0, 0]
    assert plan.num_points_inside == 5 and plan.nnz == 3
    # (d, cell) = (0, 0), (1, 0) share voxel 2 and (0, 1), (2, 1) voxel 0: two pairs of two points
    depth = torch.tensor([1.0, 10.0, 100.0, 1000.0, 10000.0, 100000.0])  # flat (d, cell)
    assert plan.pair_values(depth).tolist() == [10.0 + 100000.0, 1.0 + 100.0, 10000.0]
    a = plan.matrix(plan.pair_values(depth)).to_dense()
    torch.testing.assert_close(plan.matrix_t(plan.pair_values(depth)).to_dense(), a.t())


def test_empty_plan_gives_zeros_and_zero_gradients() -> None:
    plan = build_splat_plan(torch.full((2, 3, 2, 2), -1), 5)
    depth = torch.rand(1, 2, 3, 2, 2, requires_grad=True)
    context = torch.rand(1, 2, 4, 2, 2, requires_grad=True)
    out = splat_outer(depth, context, [plan])
    assert out.shape == (1, 4, 5) and not out.any()
    out.sum().backward()
    assert not depth.grad.any() and not context.grad.any()


def test_plan_rejects_bad_indices() -> None:
    with pytest.raises(ValueError, match="outside"):
        build_splat_plan(torch.tensor([[[[5]]]]), 5)
    with pytest.raises(ValueError, match=r"\(N, D, h, w\)"):
        build_splat_plan(torch.zeros(3, dtype=torch.long), 5)


# ----------------------------------------------------------------------------- values and gradients
def _random_case(b: int, n: int, d: int, h: int, w: int, c: int, v: int, dtype: torch.dtype, seed: int):
    """Random depth/context and a random index with repeated (voxel, cell) pairs and dropped points."""
    g = torch.Generator().manual_seed(seed)
    index = torch.randint(-1, v, (b, n, d, h, w), generator=g)
    index[:, :, 1] = index[:, :, 0]  # two depth bins of every cell share a voxel: pairs with 2 points
    depth = torch.rand(b, n, d, h, w, generator=g, dtype=dtype).requires_grad_()
    context = torch.randn(b, n, c, h, w, generator=g, dtype=dtype).requires_grad_()
    return index, depth, context


def test_gradcheck_float64_tiny() -> None:
    index, depth, context = _random_case(2, 2, 3, 2, 3, 2, 7, torch.float64, seed=1)
    plans = [build_splat_plan(index[i], 7) for i in range(2)]
    assert any(p.pair is not None for p in plans)
    assert torch.autograd.gradcheck(lambda a, b: splat_outer(a, b, plans), (depth, context))
    # and each input alone (needs_input_grad paths)
    assert torch.autograd.gradcheck(lambda a: splat_outer(a, context.detach(), plans), (depth,))
    assert torch.autograd.gradcheck(lambda b: splat_outer(depth.detach(), b, plans), (context,))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_values_and_gradients_equal_the_naive_splat_on_a_bigger_case(dtype: torch.dtype) -> None:
    b, n, d, h, w, c, v = 3, 2, 12, 6, 9, 16, 300
    index, depth, context = _random_case(b, n, d, h, w, c, v, dtype, seed=2)
    plans = [build_splat_plan(index[i], v) for i in range(b)]
    grad = torch.randn(b, c, v, dtype=dtype)
    fast = splat_outer(depth, context, plans)
    fast.backward(grad)
    fast_grads = depth.grad.clone(), context.grad.clone()
    depth.grad = context.grad = None
    ref = naive_outer(depth, context, index, v)
    ref.backward(grad)
    tol = dict(atol=1e-12, rtol=1e-12) if dtype == torch.float64 else dict(atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(fast, ref, **tol)
    torch.testing.assert_close(fast_grads[0], depth.grad, **tol)
    torch.testing.assert_close(fast_grads[1], context.grad, **tol)
    assert depth.grad[index < 0].abs().max() == 0  # dropped points get no gradient


def test_lss_fast_equals_reference_on_random_augmented_geometry() -> None:
    """Whole LSS (per-cell net included): volumes and every gradient agree; B=3, N=2, augmented, partly outside."""
    batch = random_batch(3, 2, seed=3)
    fast, ref = make_lss("fast"), make_lss("reference")
    ref.load_state_dict(fast.state_dict())
    feats = torch.randn(3, 2, 4, 4, 8)
    index = ref.voxel_index(batch, 4, 8)
    assert 0.1 < (index >= 0).float().mean() < 0.9, "the geometry must put some points outside the grid"
    grads = []
    outs = []
    for lss in (fast, ref):
        x = feats.clone().requires_grad_()
        lifted = lss(x, batch)
        weight = torch.linspace(-1, 1, lifted.volume.numel()).view_as(lifted.volume)
        (lifted.volume * weight).sum().backward()
        outs.append(lifted.volume.detach())
        grads.append([x.grad] + [p.grad for p in lss.parameters()])
    assert outs[0].abs().sum() > 0
    torch.testing.assert_close(outs[0], outs[1], atol=1e-5, rtol=1e-5)
    for g_fast, g_ref in zip(grads[0], grads[1], strict=True):
        torch.testing.assert_close(g_fast, g_ref, atol=1e-5, rtol=1e-4)


# ----------------------------------------------------------------------------- cache: reuse, never stale
def test_cache_reuses_plans_and_identical_items_share_one() -> None:
    lss = make_lss("fast")
    batch = random_batch(3, 2, seed=4)
    for name in ("intrinsics", "cam_to_ego", "img_aug"):
        getattr(batch, name)[1:] = getattr(batch, name)[0]
    feats = torch.randn(1, 2, 4, 4, 8).expand(3, -1, -1, -1, -1)
    first = lss(feats, batch).volume
    assert len(lss.plan_cache) == 1 and lss.plan_cache.misses == 3 and lss.plan_cache.hits == 0
    again = lss(feats, batch).volume
    assert lss.plan_cache.hits == 3 and len(lss.plan_cache) == 1
    assert torch.equal(first, again)
    torch.testing.assert_close(first[0], first[2])  # same geometry and features -> same volume


@pytest.mark.parametrize("change", ["extrinsic", "intrinsic", "augmentation", "tiny_extrinsic"])
def test_changed_geometry_is_never_served_stale_indices(change: str) -> None:
    fast, ref = make_lss("fast"), make_lss("reference")
    ref.load_state_dict(fast.state_dict())
    batch = random_batch(2, 2, seed=5)
    feats = torch.randn(2, 2, 4, 4, 8)
    before = fast(feats, batch).volume
    misses = fast.plan_cache.misses
    if change == "extrinsic":
        batch.cam_to_ego[1, 0, 0, 3] += 0.5  # sample 1, camera 0 moves 0.5 m forward
    elif change == "intrinsic":
        batch.intrinsics[1, 1, 0, 0] *= 1.2
    elif change == "augmentation":
        batch.img_aug[1, 0, 0, 2] += 5.0  # a 5-pixel crop shift
    else:  # the smallest representable change of one translation (a different key, maybe the same voxels)
        batch.cam_to_ego[1, 1, 1, 3] = torch.nextafter(batch.cam_to_ego[1, 1, 1, 3], torch.tensor(100.0))
    after = fast(feats, batch).volume
    assert fast.plan_cache.misses == misses + 1, "only the changed sample's plan is rebuilt"
    torch.testing.assert_close(after, ref(feats, batch).volume, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(after[0], before[0])  # the untouched sample
    if change != "tiny_extrinsic":
        assert not torch.allclose(after[1], before[1]), "the moved camera must change the output"


def test_geometry_key_is_exact() -> None:
    t = torch.tensor([[1.0, 2.0], [3.0, 4.0]])
    key = geometry_key(t, h=4)
    assert key == geometry_key(t.clone(), h=4)
    bumped = t.clone()
    bumped[1, 1] = torch.nextafter(bumped[1, 1], torch.tensor(10.0))
    assert geometry_key(bumped, h=4) != key
    assert geometry_key(t, h=5) != key
    assert geometry_key(t.double(), h=4) != key
    assert geometry_key(t.reshape(4), h=4) != key


def test_cache_is_lru_bounded_and_not_copied() -> None:
    import copy

    cache = SplatPlanCache(max_entries=2)
    plans = [build_splat_plan(torch.full((1, 1, 1, 1), i), 3) for i in range(3)]
    cache.put("a", plans[0])
    cache.put("b", plans[1])
    assert cache.get("a") is plans[0]  # a is now the most recently used
    cache.put("c", plans[2])
    assert "b" not in cache and "a" in cache and "c" in cache
    assert len(copy.deepcopy(cache)) == 0
    lss = make_lss("fast")
    lss(torch.randn(1, 1, 4, 4, 8), random_batch(1, 1, seed=6))
    assert len(lss.plan_cache) == 1
    assert not any("plan" in k for k in lss.state_dict())


# ----------------------------------------------------------------------------- the public FrustumSplatter
H4, W8 = 4, 8  # feature map of the 32 x 64 images at stride 8


def naive_points(features: Tensor, index: Tensor, v: int) -> Tensor:
    """Reference: (B, N, D, C, h, w) features, (B, N, D, h, w) local index -> (B, C, V) by index_add_ over every point."""
    b, c = features.shape[0], features.shape[3]
    rows = features.permute(0, 1, 2, 4, 5, 3).reshape(-1, c)
    offset = torch.arange(b).view(b, 1, 1, 1, 1) * v
    flat = torch.where(index >= 0, index + offset, index).reshape(-1)
    return splat(rows, flat, b * v).view(b, v, c).permute(0, 2, 1)


def _case(dtype: torch.dtype, seed: int, c: int = 6):
    g = torch.Generator().manual_seed(seed)
    batch = random_batch(3, 2, seed=seed)
    depths = torch.linspace(1.5, 19.5, 10)
    feats = torch.randn(3, 2, 10, c, H4, W8, generator=g, dtype=dtype).requires_grad_()
    return batch, depths, feats


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_per_point_path_equals_naive_index_add_values_and_gradients(dtype: torch.dtype) -> None:
    batch, depths, feats = _case(dtype, seed=11)
    sp = FrustumSplatter(GRID, S)
    index = sp.cell_index(batch, H4, W8, depths)
    assert 0.1 < (index >= 0).float().mean() < 0.9
    v = sp.num_cells
    grad = torch.randn(3, 6, v, dtype=dtype)
    fast = sp.splat_points(feats, batch, depths)
    assert fast.shape == (3, 6, *GRID.shape) and fast.dtype == dtype
    fast.backward(grad.view_as(fast))
    g_fast = feats.grad.clone()
    feats.grad = None
    ref = naive_points(feats, index, v)
    ref.backward(grad)
    tol = {"atol": 1e-12, "rtol": 1e-12} if dtype == torch.float64 else {"atol": 1e-5, "rtol": 1e-5}
    torch.testing.assert_close(fast.view(3, 6, v), ref, **tol)
    torch.testing.assert_close(g_fast, feats.grad, **tol)
    dropped = (index < 0)[:, :, :, None].expand_as(feats)
    assert g_fast[dropped].abs().max() == 0 and g_fast[~dropped].abs().min() > 0
    # the splatter's own reference mode gives the same
    torch.testing.assert_close(
        FrustumSplatter(GRID, S, mode="reference").splat_points(feats, batch, depths), fast, **tol
    )


def test_per_point_gradcheck_with_repeated_pairs() -> None:
    g = torch.Generator().manual_seed(3)
    index = torch.randint(-1, 5, (2, 2, 3, 2, 2), generator=g)
    index[:, :, 1] = index[:, :, 0]  # several points of one cell in one voxel
    plans = [build_splat_plan(index[i], 5) for i in range(2)]
    feats = torch.randn(2, 2, 3, 4, 2, 2, dtype=torch.float64, generator=g, requires_grad=True)
    assert torch.autograd.gradcheck(lambda f: splat_points(f, plans), (feats,))
    torch.testing.assert_close(splat_points(feats, plans), naive_points(feats, index, 5))


def test_outer_path_equals_per_point_path_of_the_products() -> None:
    batch, depths, _ = _case(torch.float64, seed=12)
    g = torch.Generator().manual_seed(0)
    probs = torch.rand(3, 2, 10, H4, W8, generator=g, dtype=torch.float64)
    context = torch.randn(3, 2, 5, H4, W8, generator=g, dtype=torch.float64)
    sp = FrustumSplatter(GRID, S)
    outer = sp.splat_outer(probs, context, batch, depths)
    points = sp.splat_points(probs[:, :, :, None] * context[:, :, None], batch, depths)
    torch.testing.assert_close(outer, points, atol=1e-12, rtol=1e-12)
    assert sp.plan_cache.misses == 3 and sp.plan_cache.hits == 3  # the second call reused the plans


def test_bev_target_sums_each_column_of_the_3d_volume() -> None:
    batch, depths, feats = _case(torch.float64, seed=13)
    vol = FrustumSplatter(GRID, S).splat_points(feats, batch, depths)
    bev_sp = FrustumSplatter(GRID, S, bev=True)
    bev = bev_sp.splat_points(feats, batch, depths)
    assert bev.shape == (3, 6, *GRID.shape[:2]) and bev_sp.num_cells == GRID.shape[0] * GRID.shape[1]
    torch.testing.assert_close(bev, vol.sum(-1), atol=1e-12, rtol=1e-12)
    ref = FrustumSplatter(GRID, S, bev=True, mode="reference")
    torch.testing.assert_close(ref.splat_points(feats, batch, depths), bev, atol=1e-12, rtol=1e-12)


def test_per_camera_depth_centres() -> None:
    batch, _, feats = _case(torch.float64, seed=14)
    per_cam = torch.stack([torch.linspace(1.5, 19.5, 10), torch.logspace(0.1, 1.3, 10)])  # (N, D), two spacings
    sp = FrustumSplatter(GRID, S)
    out = sp.splat_points(feats, batch, per_cam)
    # camera by camera with a shared (D,) vector: the sum over cameras is the two-camera result
    parts = []
    for n in range(2):
        one = hand_batch(
            3,
            images=batch.images[:, n : n + 1],
            intrinsics=batch.intrinsics[:, n : n + 1],
            cam_to_ego=batch.cam_to_ego[:, n : n + 1],
            img_aug=batch.img_aug[:, n : n + 1],
        )
        parts.append(FrustumSplatter(GRID, S).splat_points(feats[:, n : n + 1], one, per_cam[n]))
    torch.testing.assert_close(out, parts[0] + parts[1], atol=1e-12, rtol=1e-12)
    pts = frustum_points(batch, H4, W8, S, per_cam)
    assert pts.shape == (3, 2, 10, H4, W8, 3)
    # (B, N, D) too; and a bad shape or a non-monotone vector is one clear error
    torch.testing.assert_close(sp.splat_points(feats, batch, per_cam.expand(3, 2, 10)), out)
    with pytest.raises(ValueError, match=r"\(D,\), \(N, D\) or \(B, N, D\)"):
        sp.splat_points(feats, batch, torch.ones(3, 10))
    with pytest.raises(ValueError, match="strictly increasing"):
        sp.splat_points(feats, batch, torch.linspace(19.5, 1.5, 10))


def test_point_to_index_hook_replaces_the_grid_indexing() -> None:
    batch, depths, feats = _case(torch.float64, seed=15)
    shifted = GridSpec(range=(-11.2, -12.0, -1.0, 12.8, 12.0, 4.6), voxel_size=0.8)  # GRID moved +0.8 m in x

    def hook(points: Tensor) -> Tensor:  # index on a grid shifted by one voxel
        return GRID.coord_to_index(points - torch.tensor([0.8, 0.0, 0.0]))

    via_hook = FrustumSplatter(GRID, S, point_to_index=hook).splat_points(feats, batch, depths)
    direct = FrustumSplatter(shifted, S).splat_points(feats, batch, depths)
    torch.testing.assert_close(via_hook, direct)
    sp = FrustumSplatter(GRID, S)
    sp.splat_points(feats, batch, depths)
    sp.point_to_index = hook
    assert len(sp.plan_cache) == 0  # a new hook never meets a stale plan
    torch.testing.assert_close(sp.splat_points(feats, batch, depths), direct)


def test_a_point_1km_away_lands_in_the_outer_cell_of_a_contracted_grid() -> None:
    # One camera at ego (0, 0.2, 1.5) looking along +x; principal point on cell (0, 0)'s centre of a 1 x 1 feature map.
    # y = 0.2 and x = 1200 keep every point inside a cell: at y = 0 or x = 1000 (x' = 78.4) a point sits on a voxel
    # face and the cell it lands in turns on the last float bit, which differs between CPUs.
    cam = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    batch = hand_batch(
        1,
        images=torch.zeros(1, 1, 3, 8, 8),
        intrinsics=torch.tensor([[[[10.0, 0, 3.5], [0, 10.0, 3.5], [0, 0, 1]]]]),
        cam_to_ego=make_pose(cam, torch.tensor([0.0, 0.2, 1.5])).view(1, 1, 4, 4),
    )
    contracted = GridSpec(range=(-80, -80, -1, 80, 80, 5.4), voxel_size=(0.8, 0.8, 0.4), contraction={"near": 40.0})
    metric = GridSpec(range=(-80, -80, -1, 80, 80, 5.4), voxel_size=(0.8, 0.8, 0.4))
    depths = torch.tensor([10.0, 60.0, 1200.0])
    feats = torch.tensor([1.0, 10.0, 100.0]).view(1, 1, 3, 1, 1, 1)
    out = FrustumSplatter(contracted, 8).splat_points(feats, batch, depths)[0, 0]
    # x = 10 -> cell 112; x = 60 -> x' = 80 (1 - 0.5 / 1.5) = 53.33 -> cell 166; x = 1200 -> x' = 78.67 -> cell 198
    assert out[112, 100, 6] == 1.0 and out[166, 100, 6] == 10.0 and out[198, 100, 6] == 100.0
    assert out.sum() == 111.0
    # With 1.6 m cells (100 x 100 BEV) 1.2 km and 1000 km both land in the outer cell 99, never dropped
    # (10 m -> cell floor(90 / 1.6) = 56); the metric grid drops everything beyond 80 m.
    coarse = GridSpec(range=(-80, -80, -1, 80, 80, 5.4), voxel_size=(1.6, 1.6, 0.4), contraction={"near": 40.0})
    far = FrustumSplatter(coarse, 8, bev=True).splat_points(feats, batch, torch.tensor([10.0, 1.2e3, 1e6]))[0, 0]
    assert far.shape == (100, 100) and far[56, 50] == 1.0 and far[99, 50] == 10.0 + 100.0 and far.sum() == 111.0
    assert FrustumSplatter(metric, 8).splat_points(feats, batch, depths)[0, 0].sum() == 11.0


def test_voxel_assignment_does_not_depend_on_the_matmul_kernel() -> None:
    """Cells equal an exact reference computed another way (float64, ``solve`` instead of an inverse).

    Exported graphs run the same geometry on other kernels (onnxruntime, another CPU); in float32 a
    point within an ulp of a voxel face changes side with the summation order, which moved logits
    by ~5e-4 in an ONNX parity check. The splatter unprojects in float64, so no point lies that close.
    """
    batch = random_batch(4, 3, seed=11)
    depths = torch.arange(1.0, 21.0, 0.125)  # 160 depths x every pixel x 12 cameras: ~3.9 M points
    splatter = FrustumSplatter(GRID, 1)
    got = splatter.cell_index(batch, H, W, depths)

    b, n = batch.cam_to_ego.shape[:2]
    k = (batch.img_aug.double() @ batch.intrinsics.double()).view(b, n, 1, 3, 3)
    v, u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    uv1 = torch.stack([u, v, torch.ones_like(u)], -1).double().view(1, 1, -1, 3, 1)
    rays = torch.linalg.solve(k, uv1)[..., 0]  # (B, N, hw, 3)
    cam = rays[:, :, None] / rays[:, :, None, :, 2:] * depths.double().view(1, 1, -1, 1, 1)  # (B, N, D, hw, 3)
    pose = batch.cam_to_ego.double().view(b, n, 1, 1, 4, 4)
    ego = (pose[..., :3, :3] @ cam[..., None])[..., 0] + pose[..., :3, 3]
    lower = torch.tensor(GRID.lower, dtype=torch.float64)
    idx = torch.floor((ego - lower) / torch.tensor(GRID.voxel_size, dtype=torch.float64)).long()
    shape = torch.tensor(GRID.shape)
    inside = ((idx >= 0) & (idx < shape)).all(-1)
    flat = (idx[..., 0] * shape[1] + idx[..., 1]) * shape[2] + idx[..., 2]
    want = torch.where(inside, flat, torch.full_like(flat, -1)).view_as(got)
    assert 0.05 < float(inside.double().mean()) < 0.95
    assert int((got != want).sum()) == 0
