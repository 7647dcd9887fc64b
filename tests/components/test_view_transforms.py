"""View transforms: LSS frustum geometry and splat, backward projection sampling, swapability.

The rig: cameras at ego (0, 0, 1.5) looking along +x (OpenCV camera: x right = ego -y,
y down = ego -z, z forward = ego +x), focal 40 px, on 32 x 64 images at stride 8 (4 x 8 cells).
The principal point sits on the centre of cell (r, c) = (2, 4): u = 8*4 + 3.5, v = 8*2 + 3.5,
so an ego point (X, Y, Z) projects to u = 35.5 - 40 Y / X, v = 19.5 - 40 (Z - 1.5) / X.
"""

from __future__ import annotations

import pytest
import torch
from torch import Tensor, nn

from occplug.components import BackwardProjection, DepthAndContext, DepthNet, LSSViewTransform, splat
from occplug.components.view_transforms import (
    depth_bin_centers,
    frustum_points,
    voxel_flat_index,
)
from occplug.data.frame import Batch
from occplug.geometry import GridSpec, make_pose, project_to_image, unproject_from_image
from occplug.testing import hand_batch
from occplug.testing.conformance import tiny_context

H, W, S, F = 32, 64, 8, 40.0
CAM_TO_EGO_R = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def make_batch(b: int = 1, n: int = 1, height: int = H, width: int = W, img_aug: Tensor | None = None) -> Batch:
    k = torch.tensor([[F, 0.0, 35.5], [0.0, F, 19.5], [0.0, 0.0, 1.0]])
    pose = make_pose(CAM_TO_EGO_R, torch.tensor([0.0, 0.0, 1.5]))
    aug = torch.eye(3) if img_aug is None else img_aug
    return hand_batch(
        b,
        images=torch.rand(b, n, 3, height, width),
        intrinsics=k.expand(b, n, 3, 3).clone(),
        cam_to_ego=pose.expand(b, n, 4, 4).clone(),
        img_aug=aug.expand(b, n, 3, 3).clone(),
    )


# Offset so that no frustum point of the rig sits exactly on a voxel face (float round-off could flip it).
GRID = GridSpec(range=(0.13, -8.07, -1.03, 16.13, 7.93, 5.37), voxel_size=0.8)


class FixedOutput(DepthNet):
    """Stands in for a depth net: a fixed (learnable) ``(B*N, D + C, h, w)`` tensor split into depth logits and context."""

    def __init__(self, value: Tensor, num_bins: int) -> None:
        super().__init__()
        self.value = nn.Parameter(value)
        self.num_bins, self.out_channels = num_bins, value.shape[1] - num_bins

    def forward(self, x: Tensor, batch: Batch) -> DepthAndContext:
        out = (self.value + 0.0 * x.sum()).view(*x.shape[:2], *self.value.shape[1:])
        return DepthAndContext(out[:, :, : self.num_bins], out[:, :, self.num_bins :])


# ----------------------------------------------------------------------------- LSS geometry
def test_depth_bin_centers() -> None:
    centers = depth_bin_centers([1.0, 45.0, 1.0])
    assert centers.shape == (44,)
    torch.testing.assert_close(centers, torch.arange(44, dtype=torch.float32) + 1.5)
    torch.testing.assert_close(depth_bin_centers([2.0, 4.0, 0.5]), torch.tensor([2.25, 2.75, 3.25, 3.75]))
    with pytest.raises(ValueError, match="whole number of bins"):
        depth_bin_centers([1.0, 4.5, 1.0])
    with pytest.raises(ValueError, match="start, stop, step"):
        depth_bin_centers([1.0, 4.0])


def test_frustum_known_values_and_round_trip() -> None:
    batch = make_batch()
    depths = torch.tensor([2.0, 10.0])
    pts = frustum_points(batch, 4, 8, S, depths)  # (1, 1, 2, 4, 8, 3)
    # cell (2, 4) is on the optical axis: straight ahead at camera height
    torch.testing.assert_close(pts[0, 0, :, 2, 4], torch.tensor([[2.0, 0.0, 1.5], [10.0, 0.0, 1.5]]))
    # cell (0, 0): centre pixel (3.5, 3.5) -> Y = (35.5 - 3.5) X / 40, Z = 1.5 + (19.5 - 3.5) X / 40
    torch.testing.assert_close(pts[0, 0, 1, 0, 0], torch.tensor([10.0, 8.0, 5.5]))
    uv, z = project_to_image(pts.view(1, 1, -1, 3), batch.intrinsics, batch.cam_to_ego, batch.img_aug)
    cells_u = (torch.arange(8.0) * S + (S - 1) / 2).expand(2, 4, 8)
    cells_v = (torch.arange(4.0) * S + (S - 1) / 2).view(4, 1).expand(2, 4, 8)
    torch.testing.assert_close(uv.view(2, 4, 8, 2)[..., 0], cells_u)
    torch.testing.assert_close(uv.view(2, 4, 8, 2)[..., 1], cells_v)
    torch.testing.assert_close(z.view(2, 4, 8), depths.view(2, 1, 1).expand(2, 4, 8))


def test_splat_sums_features_per_voxel_and_drops_outside() -> None:
    torch.manual_seed(0)
    feats = torch.randn(50, 3)
    index = torch.randint(-1, 7, (50,))
    out = splat(feats, index, 7)
    expected = torch.zeros(7, 3)
    for m in range(50):
        if index[m] >= 0:
            expected[index[m]] += feats[m]
    torch.testing.assert_close(out, expected)
    torch.testing.assert_close(out.sum(0), feats[index >= 0].sum(0))


def test_voxel_flat_index_matches_grid_indexing() -> None:
    grid = GridSpec(range=(0, 0, 0, 3, 2, 2), voxel_size=1.0)
    pts = torch.tensor(
        [[[0.5, 0.5, 0.5], [2.5, 1.5, 1.5], [3.5, 0.5, 0.5]], [[0.5, 0.5, 0.5], [-0.1, 0.5, 0.5], [1.2, 0.2, 1.7]]]
    )
    idx = voxel_flat_index(pts, grid)
    # ((b*X + i)*Y + j)*Z + k with (X, Y, Z) = (3, 2, 2)
    assert idx.tolist() == [[0, 11, -1], [12, -1, 12 + 4 + 1]]


def _one_hot_lss(batch: Batch, depth_bins: list[float], channels: int) -> tuple[LSSViewTransform, Tensor, Tensor]:
    """An LSS whose per-cell net outputs a one-hot depth (bin (r*w + c) % D) and context = cell id * (1, 2, ...)."""
    lss = LSSViewTransform(in_channels=4, image_stride=S, grid=GRID, out_channels=channels, depth_bins=depth_bins)
    d, h, w = lss.num_depth_bins, 4, 8
    cell = torch.arange(h * w).view(h, w)
    chosen = cell % d
    logits = torch.full((d, h, w), -1e4).scatter_(0, chosen[None], 1e4)
    context = (cell[None].float() + 1) * torch.arange(1.0, channels + 1).view(-1, 1, 1)
    lss.depth_net = FixedOutput(torch.cat([logits, context])[None].expand(len(batch), d + channels, h, w).clone(), d)
    return lss, chosen, context


def test_lss_one_hot_depth_lands_in_the_unprojected_voxel() -> None:
    batch = make_batch()
    bins = [1.0, 21.0, 2.0]  # centres 2, 4, ..., 20: beyond 16 m falls outside the grid
    lss, chosen, context = _one_hot_lss(batch, bins, channels=2)
    lifted = lss(torch.zeros(1, 1, 4, 4, 8), batch)
    assert lifted.volume.shape == (1, 2, *GRID.shape)
    assert lifted.depth_probs.shape == (1, 1, 10, 4, 8)
    torch.testing.assert_close(lifted.depth_bins, depth_bin_centers(bins))

    # Independent expectation: unproject each cell centre at its chosen bin centre, find the voxel.
    centers = depth_bin_centers(bins)
    expected = torch.zeros(2, *GRID.shape)
    landed = 0
    for r in range(4):
        for c in range(8):
            uv = torch.tensor([[[S * c + (S - 1) / 2, S * r + (S - 1) / 2]]])
            depth = centers[chosen[r, c]].view(1, 1)
            point = unproject_from_image(uv, depth, batch.intrinsics[0], batch.cam_to_ego[0], batch.img_aug[0])[0, 0]
            if GRID.contains(point):
                i, j, k = GRID.coord_to_index(point).tolist()
                expected[:, i, j, k] += context[:, r, c]
                landed += 1
    assert 0 < landed < 32  # some cells land inside, some beyond the grid
    torch.testing.assert_close(lifted.volume[0], expected)


def test_lss_conserves_features_inside_the_grid_and_backpropagates() -> None:
    torch.manual_seed(0)
    batch = make_batch(b=2, n=2)
    lss = LSSViewTransform(
        in_channels=4, image_stride=S, grid=GRID, out_channels=3, depth_bins=[1.0, 25.0, 1.0], hidden=8
    )
    d = lss.num_depth_bins
    net_out = torch.randn(4, d + 3, 4, 8)
    lss.depth_net = FixedOutput(net_out, d)
    lifted = lss(torch.zeros(2, 2, 4, 4, 8), batch)
    probs = net_out[:, :d].softmax(1).view(2, 2, d, 4, 8)
    torch.testing.assert_close(lifted.depth_probs, probs)
    torch.testing.assert_close(lifted.depth_probs.sum(2), torch.ones(2, 2, 4, 8))
    inside = (lss.voxel_index(batch, 4, 8) >= 0).float()  # (B, N, D, h, w)
    context = net_out[:, d:].view(2, 2, 3, 4, 8)
    kept = torch.einsum("bndhw,bnchw->bc", probs * inside, context)
    torch.testing.assert_close(lifted.volume.sum(dim=(2, 3, 4)), kept)
    assert 0 < inside.mean() < 1

    lifted.volume.square().sum().backward()
    grad = lss.depth_net.value.grad
    assert grad[:, :d].abs().sum() > 0, "no gradient reaches the depth logits"
    assert grad[:, d:].abs().sum() > 0, "no gradient reaches the context features"


def test_lss_gradient_reaches_image_features() -> None:
    torch.manual_seed(0)
    batch = make_batch()
    lss = LSSViewTransform(
        in_channels=4, image_stride=S, grid=GRID, out_channels=3, depth_bins=[1.0, 25.0, 1.0], hidden=8
    )
    feats = torch.randn(1, 1, 4, 4, 8, requires_grad=True)
    lss(feats, batch).volume.square().sum().backward()
    assert feats.grad is not None and feats.grad.abs().sum() > 0


def test_lss_half_size_images_with_resize_img_aug_give_the_same_voxels() -> None:
    """Halving the images (img_aug records the resize) at half the stride keeps every frustum point."""
    full = make_batch()
    # Resizing by 0.5 maps pixel centre u to 0.5 u - 0.25 (pixel-centre convention, align_corners=False).
    resize = torch.tensor([[0.5, 0.0, -0.25], [0.0, 0.5, -0.25], [0.0, 0.0, 1.0]])
    half = make_batch(height=H // 2, width=W // 2, img_aug=resize)
    a = LSSViewTransform(in_channels=4, image_stride=S, grid=GRID, depth_bins=[1.0, 25.0, 1.0])
    b = LSSViewTransform(in_channels=4, image_stride=S // 2, grid=GRID, depth_bins=[1.0, 25.0, 1.0])
    torch.testing.assert_close(
        frustum_points(half, 4, 8, S // 2, b.depth_centers), frustum_points(full, 4, 8, S, a.depth_centers)
    )
    index = a.voxel_index(full, 4, 8)
    assert torch.equal(b.voxel_index(half, 4, 8), index)
    assert (index >= 0).any()


def test_view_transforms_reject_a_wrong_image_stride() -> None:
    batch = make_batch()
    for cls in (LSSViewTransform, BackwardProjection):
        vt = cls(in_channels=4, image_stride=4, grid=GRID)
        with pytest.raises(ValueError, match="image_stride must be the encoder's stride"):
            vt(torch.zeros(1, 1, 4, 4, 8), batch)


# ----------------------------------------------------------------------------- backward projection
# Voxels 2 m wide whose centres at X = 10 project exactly onto cell centres: 40 * 2 / 10 = 8 px = 1 cell.
BP_GRID = GridSpec(range=(-11.0, -9.0, -3.5, 11.0, 11.0, 8.5), voxel_size=2.0)  # centres X, Y: -10..10, Z: -2.5..7.5


def test_backward_projection_reads_exactly_the_cell_each_voxel_projects_onto() -> None:
    torch.manual_seed(0)
    batch = make_batch()
    bp = BackwardProjection(in_channels=4, image_stride=S, grid=BP_GRID, out_channels=3, hidden=0)
    feats = torch.randn(1, 1, 4, 4, 8)
    volume = bp(feats, batch).volume[0]  # (C, 11, 10, 6)
    projected = bp.image_net(feats[0])[0]  # (C, 4, 8)
    i10 = 10  # X = 10
    for j, y in enumerate(torch.arange(-8.0, 11.0, 2.0).tolist()):
        for k, z in enumerate(torch.arange(-2.5, 8.0, 2.0).tolist()):
            c, r = round(4 - y / 2), round(2 - (z - 1.5) / 2)
            if 0 <= c < 8 and 0 <= r < 4:
                torch.testing.assert_close(volume[:, i10, j, k], projected[:, r, c], atol=1e-5, rtol=1e-5)
            else:  # projects outside the image
                assert torch.all(volume[:, i10, j, k] == 0)
    assert torch.all(volume[:, :6] == 0), "voxels behind the camera (X <= 0) must stay empty"


def test_backward_projection_averages_over_cameras_and_points() -> None:
    batch = make_batch(n=2)
    bp = BackwardProjection(in_channels=1, image_stride=S, grid=BP_GRID, out_channels=1, hidden=0, points_per_voxel=3)
    with torch.no_grad():
        bp.image_net[0].weight.fill_(1.0)
        bp.image_net[0].bias.zero_()
    feats = torch.stack([torch.full((1, 4, 8), 2.0), torch.full((1, 4, 8), 6.0)])[None]  # camera 0: 2, camera 1: 6
    volume = bp(feats, batch).volume[0, 0]
    seen = volume != 0
    assert seen.any() and not seen[:6].any()
    torch.testing.assert_close(volume[seen], torch.full_like(volume[seen], 4.0))


def test_both_view_transforms_take_the_same_arguments_and_output_the_same_shape() -> None:
    torch.manual_seed(0)
    batch = make_batch(b=2, n=2)
    args = dict(in_channels=4, image_stride=S, grid=GRID, out_channels=5, depth_bins=[1.0, 20.0, 1.0], hidden=8)
    feats = torch.randn(2, 2, 4, 4, 8, requires_grad=True)
    shapes = []
    for cls in (LSSViewTransform, BackwardProjection):
        lifted = cls(**args)(feats, batch)
        shapes.append(lifted.volume.shape)
        assert lifted.grid == GRID
        feats.grad = None
        lifted.volume.square().sum().backward()
        assert feats.grad.abs().sum() > 0
    assert shapes[0] == shapes[1] == (2, 5, *GRID.shape)


# ----------------------------------------------------------------------------- depth nets (kind depth_net)
def test_plain_depth_net_gives_the_numbers_of_the_former_built_in_head() -> None:
    """Same seed -> the same weights as the PixelNet LSS used to build, and the same volume as its formula."""
    from occplug.nn import PixelNet

    batch = make_batch(b=2, n=2)
    torch.manual_seed(7)
    lss = LSSViewTransform(
        in_channels=4, image_stride=S, grid=GRID, out_channels=3, depth_bins=[1.0, 25.0, 1.0], hidden=8
    )
    torch.manual_seed(7)
    former = PixelNet(4, 8, 24 + 3)
    assert lss.depth_net.net.state_dict().keys() == former.state_dict().keys()
    for key, value in former.state_dict().items():
        assert torch.equal(lss.depth_net.net.state_dict()[key], value), key
    feats = torch.randn(2, 2, 4, 4, 8)
    lifted = lss(feats, batch)
    out = former(feats.flatten(0, 1))
    probs = out[:, :24].softmax(1).view(2, 2, 24, 4, 8)
    torch.testing.assert_close(lifted.depth_probs, probs, atol=0, rtol=0)
    ref = LSSViewTransform(
        in_channels=4,
        image_stride=S,
        grid=GRID,
        out_channels=3,
        depth_bins=[1.0, 25.0, 1.0],
        hidden=8,
        splat="reference",
    )
    ref.load_state_dict(lss.state_dict())
    frustum = (
        (probs.view(2, 2, 24, 1, 4, 8) * out[:, 24:].view(2, 2, 1, 3, 4, 8)).permute(0, 1, 2, 4, 5, 3).reshape(-1, 3)
    )
    x, y, z = GRID.shape
    expected = (
        splat(frustum, lss.voxel_index(batch, 4, 8).reshape(-1), 2 * x * y * z)
        .view(2, x, y, z, 3)
        .permute(0, 4, 1, 2, 3)
    )
    torch.testing.assert_close(ref(feats, batch).volume, expected, atol=0, rtol=0)  # the reference path: bit-identical
    torch.testing.assert_close(lifted.volume, expected, atol=1e-5, rtol=1e-5)


def test_camera_vector_known_values() -> None:
    from occplug.components.depth_nets import camera_vector

    half = torch.tensor([[0.5, 0.0, -0.25], [0.0, 0.5, -0.25], [0.0, 0.0, 1.0]])  # resize by 1/2 about pixel centres
    batch = make_batch(b=1, n=1, height=16, width=32, img_aug=half)
    vec = camera_vector(batch)
    assert vec.shape == (1, 1, 18)
    # effective K = [[20, 0, 17.5], [0, 20, 9.5]]: row 0 / W = 32, row 1 / H = 16
    torch.testing.assert_close(vec[0, 0, :6], torch.tensor([20 / 32, 0.0, 17.5 / 32, 0.0, 20 / 16, 9.5 / 16]))
    torch.testing.assert_close(vec[0, 0, 6:15], CAM_TO_EGO_R.reshape(9))
    torch.testing.assert_close(vec[0, 0, 15:], torch.tensor([0.0, 0.0, 1.5]))


def test_camera_aware_depth_net_is_gated_by_the_calibration() -> None:
    from occplug.components import CameraAwareDepthNet

    torch.manual_seed(0)
    net = CameraAwareDepthNet(in_channels=4, num_bins=6, out_channels=3, hidden=8, camera_hidden=16, depth_blocks=1)
    net.eval()
    feats = torch.randn(1, 1, 4, 4, 8).expand(1, 2, 4, 4, 8)
    batch = make_batch(b=1, n=2)
    logits, context = net(feats, batch)
    assert logits.shape == (1, 2, 6, 4, 8) and context.shape == (1, 2, 3, 4, 8)
    # same features, same camera -> same output; a moved camera or a different focal length changes it
    torch.testing.assert_close(logits[0, 0], logits[0, 1])
    moved = make_batch(b=1, n=2)
    moved.cam_to_ego[0, 1, 1, 3] = 0.7
    moved.intrinsics[0, 0, 0, 0] = 55.0
    logits2, context2 = net(feats, moved)
    assert not torch.allclose(logits2[0, 1], logits[0, 1]) and not torch.allclose(context2[0, 0], context[0, 0])
    # With gates forced open (last MLP layer 0, bias +30: sigmoid = 1) it is the ungated conv stack exactly.
    with torch.no_grad():
        for gate in (net.depth_gate, net.context_gate):
            gate.mlp[-1].weight.zero_()
            gate.mlp[-1].bias.fill_(30.0)
        x = net.reduce(feats.flatten(0, 1))
        want_logits = net.depth_head(net.depth_blocks(x)).view(1, 2, 6, 4, 8)
        want_context = net.context_head(x).view(1, 2, 3, 4, 8)
        got_logits, got_context = net(feats, moved)
    torch.testing.assert_close(got_logits, want_logits)
    torch.testing.assert_close(got_context, want_context)


def test_lss_with_a_camera_aware_depth_net_trains_its_gates() -> None:
    torch.manual_seed(0)
    batch = make_batch(b=1, n=2)
    lss = LSSViewTransform(
        in_channels=4,
        image_stride=S,
        grid=GRID,
        out_channels=3,
        depth_bins=[1.0, 25.0, 1.0],
        hidden=8,
        depth_net={"type": "camera_aware", "camera_hidden": 8},
        context=tiny_context(GRID),  # the depth-net node is built through the run context
    )
    assert type(lss.depth_net).__name__ == "CameraAwareDepthNet" and lss.depth_net.num_bins == 24
    assert lss.depth_net.reduce[0].out_channels == 8  # LSS's hidden reached the depth net
    lss(torch.randn(1, 2, 4, 4, 8), batch).volume.square().sum().backward()
    assert lss.depth_net.depth_gate.mlp[0].weight.grad.abs().sum() > 0
    assert lss.depth_net.context_gate.mlp[0].weight.grad.abs().sum() > 0


def test_depth_net_node_is_validated_with_the_config() -> None:
    from pathlib import Path

    from occplug.config import ConfigError, compose, validate
    from occplug.plugins import get_registry

    root = Path(__file__).resolve().parents[2]
    cfg = compose([str(root / "configs" / "baseline.yaml")]).resolved()
    cfg["model"]["view_transform"]["depth_net"] = {"type": "camera_aware", "depth_blocks": 2}
    used = validate(cfg, get_registry())
    assert any(u.kind == "depth_net" and u.type == "camera_aware" for u in used)
    cfg["model"]["view_transform"]["depth_net"] = {"type": "camera_awar"}
    with pytest.raises(
        ConfigError, match=r"model.view_transform.depth_net.type: no depth_net named 'camera_awar'.*camera_aware"
    ):
        validate(cfg, get_registry())
    cfg["model"]["view_transform"]["depth_net"] = {"type": "plain", "hiden": 3}
    with pytest.raises(ConfigError, match=r"model.view_transform.depth_net.hiden: .*did you mean 'hidden'"):
        validate(cfg, get_registry())


def test_lss_on_a_contracted_grid_keeps_far_mass() -> None:
    """A contracted LSS grid keeps every frustum point inside its z range: the volume sums the whole (z-valid) frustum."""
    torch.manual_seed(0)
    batch = make_batch(b=1, n=1)
    grid = GridSpec((-8.0, -8.0, -1.03, 8.0, 8.0, 5.37), 0.8, contraction={"near": 4.0, "kappa": 0.5})
    lss = LSSViewTransform(
        in_channels=4, image_stride=S, grid=grid, out_channels=2, depth_bins=[1.0, 45.0, 1.0], hidden=8
    )
    assert lss.grid.is_contracted
    lifted = lss(torch.randn(1, 1, 4, 4, 8), batch)
    pts = frustum_points(batch, 4, 8, S, lss.depth_centers)
    z_ok = ((pts[..., 2] >= -1.03) & (pts[..., 2] < 5.37)).float()  # (1, 1, D, h, w)
    kept = (lifted.depth_probs * z_ok).sum()
    assert 0.3 < float(z_ok.mean()) < 1.0  # some points leave through the floor or the ceiling, none sideways
    ones = LSSViewTransform(
        in_channels=4, image_stride=S, grid=grid, out_channels=2, depth_bins=[1.0, 45.0, 1.0], hidden=0
    )
    with torch.no_grad():
        ones.depth_net.net[0].weight.zero_()
        ones.depth_net.net[0].bias.zero_()
        ones.depth_net.net[0].bias[44:] = 1.0  # uniform depth, context 1
    vol = ones(torch.randn(1, 1, 4, 4, 8), batch).volume
    torch.testing.assert_close(vol[0, 0].sum(), z_ok.sum() / 44)
    assert kept > 0
