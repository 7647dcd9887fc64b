"""OccLE's geometric branch against its definition (OccLE §3.3.1 Eq. 3-4, Tab. 4(a), §3.2 voxelisation)."""

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from occplug.geometry import GridSpec
from occplug_occle.blocks.geometry_branch import (
    Conv3dDeformableBaseline,
    CrossPlaneFusion,
    CrossPlaneGeometryBranch,
    FrameFusion,
    LidarVoxelEncoder,
    cross_plane_product,
    voxelize_points,
)

# A toy grid of shape (X, Y, Z) = (8, 6, 4), 1 m voxels, x in [0, 8), y in [-3, 3), z in [-1, 3).
GRID = GridSpec((0.0, -3.0, -1.0, 8.0, 3.0, 3.0), 1.0)
X, Y, Z = GRID.shape


def _inputs(b=2, t=2, cl=4, ci=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(b, t, cl, X, Y, Z, generator=g), torch.randn(b, t, ci, X, Y, Z, generator=g)


def _zero_attention(m: CrossPlaneFusion) -> None:
    """Make both SA terms of Eq. 3 vanish (SA's output projection is zero), so ``yz_y = yz_z = yz``."""
    for attn in (m.attend_y, m.attend_z):
        nn.init.zeros_(attn.out_proj.weight)
        nn.init.zeros_(attn.out_proj.bias)


def _sum_collapse(conv: nn.Conv2d, channels: int, n: int) -> None:
    """Make a 1x1 collapse Conv2D sum the stacked axis: out[c] = sum_n in[c * n_axis + n]."""
    with torch.no_grad():
        conv.weight.zero_()
        conv.bias.zero_()
        for c in range(channels):
            conv.weight[c, c * n : (c + 1) * n, 0, 0] = 1.0


def test_plane_shapes_of_eq3_and_eq4():
    m = CrossPlaneFusion(4, 5, GRID, channels=4, num_frames=2)
    lidar, image = _inputs()
    p = m.planes(lidar, image)
    assert p.lidar.shape == (2, 4, X, Y, Z) and p.image.shape == (2, 5, X, Y, Z)
    assert p.xz.shape == (2, 4, X, Z)
    assert p.xy.shape == (2, 4, X, Y)
    assert p.yz.shape == p.yz_y.shape == p.yz_z.shape == (2, 4, Y, Z)
    assert m(lidar, image).shape == (2, 4, X, Y, Z)
    # a list of T grids is the same input as the stacked tensor
    assert torch.equal(m(list(lidar.unbind(1)), list(image.unbind(1))), m(lidar, image))
    # Eq. 4 pairs each LiDAR plane with the image plane attended along the axis they share
    out = m(lidar, image)
    assert torch.equal(out, cross_plane_product(p.xz, p.xy, p.yz_y, p.yz_z))
    assert not torch.allclose(out, cross_plane_product(p.xz, p.xy, p.yz_z, p.yz_y))
    with pytest.raises(ValueError, match="expected grids"):
        m(lidar[:, :1], image)


def test_stacking_an_axis_puts_channel_c_at_index_n_into_channel_c_times_n_plus_n():
    c = 3
    m = CrossPlaneFusion(c, c, GRID, channels=c, num_frames=1, plane_kernel=1, heads=1)
    picks = {m.lidar_to_xz: (Y, 4), m.lidar_to_xy: (Z, 2), m.image_to_yz: (X, 6)}
    with torch.no_grad():
        for conv, (n, at) in picks.items():  # read index `at` of the stacked axis
            conv.weight.zero_()
            conv.bias.zero_()
            for ch in range(c):
                conv.weight[ch, ch * n + at, 0, 0] = 1.0
    lidar, image = _inputs(b=1, t=1, cl=c, ci=c, seed=4)
    p = m.planes(lidar, image)
    assert torch.allclose(p.xz, p.lidar[:, :, :, 4, :])
    assert torch.allclose(p.xy, p.lidar[:, :, :, :, 2])
    assert torch.allclose(p.yz, p.image[:, :, 6])


def test_frame_fusion_is_a_conv1d_over_each_voxels_frames():
    torch.manual_seed(0)
    fuse = FrameFusion(3, 4)
    grids = torch.randn(2, 4, 3, X, Y, Z)
    per_voxel = grids.permute(0, 3, 4, 5, 2, 1).reshape(-1, 3, 4)  # (B*X*Y*Z, C, T)
    ref = fuse.conv(per_voxel).view(2, X, Y, Z, 3).permute(0, 4, 1, 2, 3)
    assert torch.allclose(fuse(grids), ref, atol=1e-5)


def test_cross_plane_product_matches_eq4_written_out():
    g = torch.Generator().manual_seed(1)
    b, c = 2, 3
    xz, xy = torch.randn(b, c, X, Z, generator=g), torch.randn(b, c, X, Y, generator=g)
    yz_y, yz_z = torch.randn(b, c, Y, Z, generator=g), torch.randn(b, c, Y, Z, generator=g)
    out = cross_plane_product(xz, xy, yz_y, yz_z)
    ref = torch.empty(b, c, X, Y, Z)
    for x in range(X):
        for y in range(Y):
            for z in range(Z):
                # F_f1 = F_xz x F_yz,z (shared z) + F_f2 = F_xy x F_yz,y (shared y)
                ref[:, :, x, y, z] = xz[:, :, x, z] * yz_z[:, :, y, z] + xy[:, :, x, y] * yz_y[:, :, y, z]
    assert torch.allclose(out, ref, atol=1e-6)


def test_fusion_with_identity_like_weights_equals_a_hand_written_reference():
    # Frame Conv1D = the frame mean, collapse Conv2Ds = sums over the stacked axis, SA = 0: then
    # F_f[c,x,y,z] = (sum_y' L)[c,x,z] * (sum_x' I)[c,y,z] + (sum_z' L)[c,x,y] * (sum_x' I)[c,y,z].
    c, t = 4, 2
    m = CrossPlaneFusion(c, c, GRID, channels=c, num_frames=t, plane_kernel=1)
    with torch.no_grad():
        for fuse in (m.lidar_frames, m.image_frames):
            fuse.conv.weight.copy_(torch.eye(c)[:, :, None].expand(c, c, t) / t)
            fuse.conv.bias.zero_()
    _sum_collapse(m.lidar_to_xz, c, Y)
    _sum_collapse(m.lidar_to_xy, c, Z)
    _sum_collapse(m.image_to_yz, c, X)
    _zero_attention(m)
    lidar, image = _inputs(b=1, t=t, cl=c, ci=c, seed=3)
    out = m(lidar, image)
    lm, im = lidar.mean(1)[0], image.mean(1)[0]  # (C, X, Y, Z)
    ref = torch.zeros(c, X, Y, Z)
    for ch in range(c):
        for x in range(X):
            for y in range(Y):
                for z in range(Z):
                    xz = sum(lm[ch, x, yy, z] for yy in range(Y))
                    xy = sum(lm[ch, x, y, zz] for zz in range(Z))
                    yz = sum(im[ch, xx, y, z] for xx in range(X))
                    ref[ch, x, y, z] = xz * yz + xy * yz
    assert torch.allclose(out[0], ref, rtol=1e-4, atol=1e-4)


def test_axial_attention_attends_along_y_per_z_row_and_along_z_per_y_column():
    torch.manual_seed(0)
    m = CrossPlaneFusion(4, 4, GRID, channels=8, heads=2).eval()
    yz = torch.randn(2, 8, Y, Z)
    yz_y, yz_z = m.axial_attention(yz)
    for z in range(Z):  # Eq. 3 first line: F_yzy = F_yz + SA(F_yz), the Y tokens of one z row
        tokens = yz[:, :, :, z].transpose(1, 2)  # (B, Y, C)
        ref = tokens + m.attend_y(tokens, tokens, tokens, need_weights=False)[0]
        assert torch.allclose(yz_y[:, :, :, z], ref.transpose(1, 2), atol=1e-5)
    for y in range(Y):  # second line: F_yzz = F_yz + SA(F_yz^T)^T, the Z tokens of one y column
        tokens = yz[:, :, y, :].transpose(1, 2)  # (B, Z, C)
        ref = tokens + m.attend_z(tokens, tokens, tokens, need_weights=False)[0]
        assert torch.allclose(yz_z[:, :, y, :], ref.transpose(1, 2), atol=1e-5)


def test_a_change_in_one_yz_cell_reaches_only_voxels_with_that_y_z():
    g = torch.Generator().manual_seed(2)
    xz, xy = torch.randn(1, 3, X, Z, generator=g), torch.randn(1, 3, X, Y, generator=g)
    yz_y, yz_z = torch.randn(1, 3, Y, Z, generator=g), torch.randn(1, 3, Y, Z, generator=g)
    y0, z0 = 4, 1
    bump = torch.zeros(1, 3, Y, Z)
    bump[:, :, y0, z0] = 1.0
    diff = (cross_plane_product(xz, xy, yz_y + bump, yz_z + bump) - cross_plane_product(xz, xy, yz_y, yz_z)).abs()
    changed = diff.amax(dim=(0, 1)) > 0  # (X, Y, Z)
    expected = torch.zeros(X, Y, Z, dtype=torch.bool)
    expected[:, y0, z0] = True
    assert torch.equal(changed, expected)


def test_a_change_in_one_image_voxel_spreads_only_along_its_y_row_and_z_column():
    # Through the whole fusion (1x1 Conv2Ds): x is collapsed, SA along y spreads within z = z0 and SA along
    # z within y = y0; with SA switched off the change stays on the (y0, z0) line.
    torch.manual_seed(0)
    m = CrossPlaneFusion(4, 4, GRID, channels=4, num_frames=2, plane_kernel=1, heads=2).eval()
    lidar, image = _inputs(b=1, cl=4, ci=4)
    x0, y0, z0 = 5, 2, 3
    bumped = image.clone()
    bumped[:, :, :, x0, y0, z0] += 3.0
    ys, zs = torch.meshgrid(torch.arange(Y), torch.arange(Z), indexing="ij")
    with torch.no_grad():
        changed = (m(lidar, bumped) - m(lidar, image)).abs().amax(dim=(0, 1)) > 1e-6
        cross = ((ys == y0) | (zs == z0)).expand(X, Y, Z)
        assert bool(changed[cross].all()) and not bool(changed[~cross].any())
        _zero_attention(m)
        changed = (m(lidar, bumped) - m(lidar, image)).abs().amax(dim=(0, 1)) > 1e-6
    line = ((ys == y0) & (zs == z0)).expand(X, Y, Z)
    assert torch.equal(changed, line)


@pytest.mark.parametrize("model", ["cross_plane", "baseline"])
def test_gradients_reach_both_modalities_and_every_parameter(model):
    torch.manual_seed(0)
    cls = CrossPlaneGeometryBranch if model == "cross_plane" else Conv3dDeformableBaseline
    m = cls(4, 5, GRID, channels=8, num_frames=2)
    lidar, image = _inputs()
    lidar.requires_grad_(True)
    image.requires_grad_(True)
    m(lidar, image).square().mean().backward()
    assert lidar.grad.abs().sum() > 0 and image.grad.abs().sum() > 0
    missing = [n for n, p in m.named_parameters() if p.grad is None or not bool(p.grad.abs().sum() > 0)]
    assert not missing


def test_branch_and_baseline_share_the_input_output_contract():
    torch.manual_seed(0)
    lidar, image = _inputs()
    kwargs = dict(lidar_channels=4, image_channels=5, grid=GRID, channels=8, num_frames=2, num_classes=3)
    for cls in (CrossPlaneGeometryBranch, Conv3dDeformableBaseline):
        m = cls(**kwargs)
        assert m(lidar, image).shape == (2, 3, X, Y, Z)
        assert m(list(lidar.unbind(1)), list(image.unbind(1))).shape == (2, 3, X, Y, Z)
        assert m.encode(lidar, image).shape == (2, 8, X, Y, Z)


def test_voxelize_puts_points_in_their_voxels_with_centre_offsets():
    pts = torch.tensor(
        [
            [0.2, -2.9, -0.9, 0.1],  # voxel (0, 0, 0), centre (0.5, -2.5, -0.5)
            [7.9, 2.5, 2.75, 0.2],  # voxel (7, 5, 3), centre (7.5, 2.5, 2.5)
            [3.5, 0.0, 0.0, 0.3],  # voxel (3, 3, 1), centre (3.5, 0.5, 0.5)
            [0.7, -2.1, -0.2, 0.4],  # voxel (0, 0, 0) again, after the first
            [8.0, 0.0, 0.0, 0.5],  # x = 8 is the upper face: outside
            [-0.1, 0.0, 0.0, 0.6],  # outside
            [1.0, 0.0, 3.5, 0.7],  # above the grid: outside
        ]
    )
    other = torch.tensor([[1.5, 1.5, 1.5, 0.9]])  # sample 1: voxel (1, 4, 2), centre (1.5, 1.5, 1.5)
    vox = voxelize_points([pts, other], GRID, max_points=3)
    assert vox.coords.tolist() == [[0, 0, 0, 0], [0, 3, 3, 1], [0, 7, 5, 3], [1, 1, 4, 2]]
    assert vox.counts.tolist() == [2, 1, 1, 1]
    assert vox.features.shape == (4, 3, 7)
    f = vox.features
    assert torch.allclose(f[0, 0], torch.tensor([0.2, -2.9, -0.9, 0.1, -0.3, -0.4, -0.4]), atol=1e-6)
    assert torch.allclose(f[0, 1], torch.tensor([0.7, -2.1, -0.2, 0.4, 0.2, 0.4, 0.3]), atol=1e-6)
    assert torch.allclose(f[1, 0], torch.tensor([3.5, 0.0, 0.0, 0.3, 0.0, -0.5, -0.5]), atol=1e-6)
    assert torch.allclose(f[2, 0], torch.tensor([7.9, 2.5, 2.75, 0.2, 0.4, 0.0, 0.25]), atol=1e-6)
    assert torch.allclose(f[3, 0], torch.tensor([1.5, 1.5, 1.5, 0.9, 0.0, 0.0, 0.0]), atol=1e-6)
    assert not f[0, 2].any() and not f[1, 1:].any()  # padding rows stay zero
    assert vox.mask.sum(1).tolist() == [2, 1, 1, 1]
    # the stored position minus the offset is the voxel centre on the core's grid
    centres = GRID.index_to_coord(vox.coords[:, 1:])
    assert torch.allclose(f[:, 0, :3] - f[:, 0, 4:], centres, atol=1e-6)


def test_a_voxel_with_40_points_keeps_its_first_35():
    g = torch.Generator().manual_seed(0)
    inside = torch.rand(40, 3, generator=g) * 0.9 + torch.tensor([2.05, 0.05, 0.05])  # voxel (2, 3, 1)
    pts = torch.cat([inside, torch.arange(40.0)[:, None]], dim=1)  # intensity = input position
    lone = torch.tensor([[5.5, -1.5, 1.5, -1.0]])
    vox = voxelize_points([torch.cat([pts[:20], lone, pts[20:]])], GRID)
    assert vox.coords.tolist() == [[0, 2, 3, 1], [0, 5, 1, 2]]
    assert vox.counts.tolist() == [35, 1]
    assert torch.equal(vox.features[0, :, 3], torch.arange(35.0))  # the first 35 in input order
    assert torch.equal(vox.features[0, :, :4], pts[:35])


def test_voxel_encoder_scatters_voxel_features_and_ignores_point_order():
    torch.manual_seed(0)
    enc = LidarVoxelEncoder(GRID, point_features=1, out_channels=6, hidden=8).eval()
    g = torch.Generator().manual_seed(0)
    scale, low = torch.tensor([6.0, 6.0, 4.0, 1.0]), torch.tensor([0.0, -3.0, -1.0, 0.0])
    pts = torch.rand(300, 4, generator=g) * scale + low  # x in [0, 6): voxels i < 6
    extra = torch.rand(100, 4, generator=g) * torch.tensor([2.0, 6.0, 4.0, 1.0]) + torch.tensor([6.0, -3, -1, 0])
    grids = enc([pts, torch.cat([extra[:50], pts, extra[50:]])])
    assert grids.shape == (2, 6, X, Y, Z)
    vox = voxelize_points([pts], GRID)
    assert int(vox.counts.max()) < 35
    occupied = torch.zeros(X, Y, Z, dtype=torch.bool)
    occupied[tuple(vox.coords[:, 1:].t())] = True
    assert not grids[0][:, ~occupied].any() and bool((grids[0][:, occupied].abs().sum(0) > 0).all())
    # a voxel's feature depends only on its own points: the extra points (x >= 6) change nothing at x < 6
    assert torch.allclose(grids[1, :, :6], grids[0, :, :6], atol=1e-6)
    shuffled = enc([pts[torch.randperm(300, generator=g)], pts.flip(0)])
    assert torch.allclose(shuffled[0], grids[0], atol=1e-6) and torch.allclose(shuffled[1], grids[0], atol=1e-6)
    grids.square().sum().backward()
    assert all(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in enc.parameters())


def _voxelnet_on_voxelized(enc: LidarVoxelEncoder, points: list[torch.Tensor]) -> torch.Tensor:
    """VoxelNet written on :func:`voxelize_points`' padded ``(V, M, D)`` block (the textbook layout): the reference."""
    vox = voxelize_points(points, GRID, enc.max_points)
    mask = vox.mask.unsqueeze(-1)
    h = enc.point_net(vox.features)
    pooled = h.masked_fill(~mask, float("-inf")).amax(1, keepdim=True)
    h = enc.voxel_net(torch.cat([h, pooled.expand_as(h)], dim=-1))
    voxel = h.masked_fill(~mask, float("-inf")).amax(1)
    dense = torch.zeros(len(points), X, Y, Z, enc.out_channels)
    dense[tuple(vox.coords.t())] = voxel
    return dense.permute(0, 4, 1, 2, 3)


def _crowded(seed: int) -> list[torch.Tensor]:
    """Two clouds with crowded voxels (up to ~80 points), points outside the grid, and a NaN padding row."""
    g = torch.Generator().manual_seed(seed)
    scale, low = torch.tensor([4.0, 3.0, 2.0, 1.0]), torch.tensor([-1.0, -1.5, -1.5, 0.0])
    a = torch.rand(900, 4, generator=g) * scale + low  # 24 voxels inside (x >= 0), the rest outside
    b = torch.rand(200, 4, generator=g) * torch.tensor([8.0, 6.0, 4.0, 1.0]) + torch.tensor([0.0, -3.0, -1.0, 0.0])
    b = torch.cat([b, torch.full((3, 4), float("nan"))])
    return [a, b]


def test_voxel_encoder_equals_voxelnet_on_voxelize_points_when_keeping_the_first_points():
    torch.manual_seed(0)
    enc = LidarVoxelEncoder(GRID, point_features=1, out_channels=6, hidden=8, max_points=35, sampling="first")
    points = _crowded(1)
    assert int(voxelize_points(points, GRID, 1000).counts.max()) > 35  # the cap matters here
    got, ref = enc(points), _voxelnet_on_voxelized(enc, points)
    assert torch.isfinite(got).all()
    torch.testing.assert_close(got, ref, atol=1e-6, rtol=0)
    (got - 1).square().sum().backward()  # the discard slot and NaN rows leave the gradients finite
    assert all(torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0 for p in enc.parameters())


def test_voxel_encoder_random_sampling_keeps_35_random_points_in_training_and_a_fixed_set_in_eval():
    torch.manual_seed(0)
    enc = LidarVoxelEncoder(GRID, point_features=1, out_channels=6, hidden=8, sampling="random")
    g = torch.Generator().manual_seed(0)
    inside = torch.rand(60, 3, generator=g) * 0.9 + torch.tensor([2.05, 0.05, 0.05])  # one voxel, 60 points
    pts = torch.cat([inside, torch.arange(60.0)[:, None]], dim=1)  # intensity = input position
    discard = X * Y * Z  # one cloud: slots 0 .. X*Y*Z - 1, then the discard slot

    def kept_points() -> frozenset:
        feat, slot = enc.slots([pts])
        chosen = feat[slot < discard, 3].tolist()
        assert len(chosen) == 35 and len(set(chosen)) == 35 and int((slot == discard).sum()) == 25
        return frozenset(chosen)

    enc.train()
    kept = [kept_points() for _ in range(20)]
    assert len(set(kept)) == 20  # a fresh subset every step
    share_late = sum(sum(i >= 35 for i in k) for k in kept) / (20 * 35)
    assert 0.25 < share_late < 0.5  # 25 of 60 points come after the first 35: ~42 % of a random subset
    enc.eval()
    fixed = [kept_points() for _ in range(2)]
    assert fixed[0] == fixed[1] and fixed[0] != frozenset(range(35))
    # padding (NaN rows) after the cloud changes nothing
    padded = torch.cat([pts, torch.full((5, 4), float("nan"))])
    torch.testing.assert_close(enc([padded]), enc([pts]))


@pytest.mark.parametrize("stride", [1, 34, 55, 89, 144, 233])
def test_eval_subset_does_not_follow_the_input_order_at_any_stride(stride):
    """A voxel's 70 points at every ``stride``-th input index: its fixed eval subset takes both halves alike."""
    enc = LidarVoxelEncoder(GRID, point_features=1, out_channels=4, hidden=4, sampling="random").eval()
    shares = []
    for offset in range(21):
        pts = torch.tensor([[-5.0, 0.0, 0.0, -1.0]]).repeat(70 * stride + offset, 1)  # outside the grid
        where = offset + stride * torch.arange(70)
        pts[where] = torch.tensor([[2.5, 0.5, 0.5, 0.0]]).repeat(70, 1)
        pts[where, 3] = torch.arange(70.0)  # intensity = order among the voxel's points
        feat, slot = enc.slots([pts])
        kept = feat[slot < X * Y * Z, 3]
        assert len(kept) == 35
        shares.append(float((kept < 35).float().mean()))
    assert 0.35 < sum(shares) / len(shares) < 0.65 and min(shares) > 0.2 and max(shares) < 0.8


def test_cross_plane_branch_loss_falls_on_a_toy_target():
    torch.manual_seed(0)
    lidar, image = _inputs(b=2, t=2, cl=4, ci=4, seed=5)
    target = (lidar[:, :, 0].mean(1) + image[:, :, 1].mean(1) > 0).long()  # (B, X, Y, Z) free / occupied
    m = CrossPlaneGeometryBranch(4, 4, GRID, channels=8, num_frames=2, num_classes=2, heads=2)
    opt = torch.optim.Adam(m.parameters(), lr=1e-2)
    losses = []
    for _ in range(40):
        loss = F.cross_entropy(m(lidar, image), target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.6 * losses[0]
