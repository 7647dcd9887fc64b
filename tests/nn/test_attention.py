"""occplug.nn's attention blocks against their definitions: deformable sampling / attention (2D, 3D) and CBAM."""

import math

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from occplug.geometry import GridSpec, sample_volume
from occplug.nn import CBAM, ChannelAttention, SpatialAttention2d, SpatialAttention3d, cbam
from occplug.nn.attention import DeformableAttention, deformable_sample, spread_directions

# A toy grid of shape (X, Y, Z) = (8, 6, 4), 1 m voxels, x in [0, 8), y in [-3, 3), z in [-1, 3).
GRID = GridSpec((0.0, -3.0, -1.0, 8.0, 3.0, 3.0), 1.0)
X, Y, Z = GRID.shape


def _shifted(value: torch.Tensor, shift: tuple[int, ...]) -> torch.Tensor:
    """``out[..., i] = value[..., i + shift]`` over the trailing grid axes, zero where ``i + shift`` is outside."""
    out = torch.zeros_like(value)
    dims = len(shift)
    src, dst = [], []
    for s, n in zip(shift, value.shape[-dims:], strict=True):
        src.append(slice(max(s, 0), n + min(s, 0)))
        dst.append(slice(max(-s, 0), n - max(s, 0)))
    out[(..., *dst)] = value[(..., *src)]
    return out


# ---------------------------------------------------------------------------------------------- deformable sampling


@pytest.mark.parametrize("size", [(5, 7), (X, Y, Z)])
def test_deformable_sampling_with_zero_offsets_is_the_identity(size):
    g = torch.Generator().manual_seed(0)
    value = torch.randn(2, 3, 4, *size, generator=g)
    weights = torch.rand(2, 3, 5, *size, generator=g).softmax(dim=2)
    out = deformable_sample(value, torch.zeros(2, 3, 5, len(size), *size), weights)
    assert torch.allclose(out, value.reshape(2, 12, *size), atol=1e-5)


@pytest.mark.parametrize(("size", "shift"), [((5, 7), (1, -2)), ((5, 7), (0, 3)), ((X, Y, Z), (-1, 2, 1))])
def test_deformable_sampling_at_integer_offsets_equals_direct_indexing(size, shift):
    g = torch.Generator().manual_seed(1)
    value = torch.randn(1, 2, 3, *size, generator=g)
    offsets = torch.tensor(shift, dtype=torch.float32).view(1, 1, 1, len(size), *[1] * len(size))
    out = deformable_sample(value, offsets.expand(1, 2, 1, len(size), *size), torch.ones(1, 2, 1, *size))
    assert torch.allclose(out, _shifted(value, shift).reshape(1, 6, *size), atol=1e-6)


def test_deformable_sampling_sums_the_weighted_samples():
    g = torch.Generator().manual_seed(2)
    value = torch.randn(1, 1, 2, 4, 6, generator=g)
    shifts = [(0, 0), (1, 0), (0, -1)]
    offsets = torch.tensor(shifts, dtype=torch.float32).view(1, 1, 3, 2, 1, 1).expand(1, 1, 3, 2, 4, 6)
    weights = torch.tensor([0.5, 0.25, 0.25]).view(1, 1, 3, 1, 1).expand(1, 1, 3, 4, 6)
    out = deformable_sample(value, offsets, weights)
    want = sum(w * _shifted(value, s) for w, s in zip((0.5, 0.25, 0.25), shifts, strict=True))
    assert torch.allclose(out, want.reshape(1, 2, 4, 6), atol=1e-6)


def test_deformable_offsets_are_in_voxels_along_x_y_z():
    # Offsets (dx, dy, dz) in voxels move each sample by dx*vx, dy*vy, dz*vz metres along the grid axes:
    # compare against the core's trilinear sampling at those points (zero outside the grid, as both pad).
    g = torch.Generator().manual_seed(1)
    grid = GridSpec((0.0, -3.0, -1.0, 8.0, 3.0, 3.0), (1.0, 0.5, 2.0))
    x, y, z = grid.shape
    value = torch.randn(1, 1, 2, x, y, z, generator=g)
    step = torch.tensor([0.5, -1.25, 0.3])
    offsets = step.view(1, 1, 1, 3, 1, 1, 1).expand(1, 1, 1, 3, x, y, z)
    out = deformable_sample(value, offsets, torch.ones(1, 1, 1, x, y, z))
    pts = grid.centers().reshape(1, -1, 3) + step * torch.tensor(grid.voxel_size)
    ref = sample_volume(value[:, 0], grid, pts).transpose(1, 2).reshape(1, 2, x, y, z)
    assert torch.allclose(out, ref, atol=1e-5)


def test_deformable_sampling_rejects_mismatched_offsets():
    with pytest.raises(ValueError, match="deformable_sample"):
        deformable_sample(torch.zeros(1, 1, 1, 4, 4), torch.zeros(1, 1, 1, 3, 4, 4), torch.zeros(1, 1, 1, 4, 4))


# ---------------------------------------------------------------------------------------------- deformable attention


@pytest.mark.parametrize("dims", [2, 3])
def test_spread_directions_are_distinct_unit_vectors(dims):
    d = spread_directions(12, dims)
    assert d.shape == (12, dims) and d.dtype == torch.float32
    assert torch.allclose(d.norm(dim=-1), torch.ones(12), atol=1e-6)
    assert torch.cdist(d, d).add(torch.eye(12) * 9).min() > 0.3
    if dims == 2:  # the ring at angles 2 pi i / n
        angle = torch.atan2(d[:, 1], d[:, 0]).remainder(2 * math.pi)
        assert torch.allclose(angle, torch.arange(12) * (2 * math.pi / 12), atol=1e-5)


def test_deformable_attention_with_zero_offsets_reads_its_values_at_the_voxel_centres():
    torch.manual_seed(0)
    attn = DeformableAttention(8, heads=2, points=3, dims=3)
    nn.init.zeros_(attn.offsets.bias)
    x = torch.randn(1, 8, X, Y, Z)
    value = attn.value(x)
    centres = GRID.centers().reshape(1, -1, 3)
    ref = sample_volume(value, GRID, centres).transpose(1, 2).reshape(value.shape)  # trilinear, at the centres
    assert torch.allclose(attn.attend(x), ref, atol=1e-5)
    assert torch.allclose(ref, value, atol=1e-5)


@pytest.mark.parametrize("dims", [2, 3])
def test_deformable_attention_shapes_parameters_and_initial_offsets(dims):
    torch.manual_seed(0)
    attn = DeformableAttention(8, heads=2, points=3, dims=dims)
    size = (5, 6, 3)[:dims]
    assert attn(torch.randn(2, 8, *size)).shape == (2, 8, *size)
    assert list(attn.state_dict())[:8] == [
        "offsets.weight", "offsets.bias", "weights.weight", "weights.bias",
        "value.weight", "value.bias", "out.weight", "out.bias",
    ]  # fmt: skip
    assert attn.offsets.out_channels == 2 * 3 * dims
    assert not attn.offsets.weight.any()
    assert torch.equal(attn.offsets.bias, spread_directions(6, dims).reshape(-1))


def test_deformable_attention_offset_order_grid_sample_lists_the_last_axis_first():
    # the same offsets, listed in the two orders, read the same samples
    torch.manual_seed(0)
    axes = DeformableAttention(4, heads=1, points=2, dims=2)
    torch.manual_seed(0)
    rev = DeformableAttention(4, heads=1, points=2, dims=2, offset_order="grid_sample")
    with torch.no_grad():
        w = torch.randn(4, 4, 1, 1)
        axes.offsets.weight.copy_(w)
        rev.offsets.weight.copy_(w.view(2, 2, 4, 1, 1).flip(1).reshape(4, 4, 1, 1))
        rev.offsets.bias.copy_(axes.offsets.bias.view(2, 2).flip(1).reshape(-1))
    x = torch.randn(1, 4, 5, 7)
    assert torch.allclose(axes.attend(x), rev.attend(x), atol=1e-6)


def test_deformable_attention_rejects_bad_arguments():
    with pytest.raises(ValueError, match="not divisible by heads"):
        DeformableAttention(6, heads=4)
    with pytest.raises(ValueError, match="dims"):
        DeformableAttention(8, dims=1)
    with pytest.raises(ValueError, match="offset_order"):
        DeformableAttention(8, offset_order="xy")  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------- CBAM


def test_channel_attention_matches_its_formula_and_is_one_half_on_zeros():
    torch.manual_seed(0)
    ca = ChannelAttention(8, reduction=4, dims=3)
    assert [tuple(p.shape) for p in ca.parameters()] == [(2, 8, 1, 1, 1), (8, 2, 1, 1, 1)]
    x = torch.randn(2, 8, 3, 4, 5)

    def mlp(v):
        return F.conv3d(F.relu(F.conv3d(v, ca[0].weight)), ca[2].weight)

    want = torch.sigmoid(mlp(x.mean((2, 3, 4), keepdim=True)) + mlp(x.amax((2, 3, 4), keepdim=True)))
    assert torch.allclose(ca(x), want, atol=1e-6)
    # a zero input has zero descriptors, and the bias-free MLP maps them to 0: M_c = sigmoid(0) = 1/2
    assert torch.equal(ca(torch.zeros(1, 8, 2, 2, 2)), torch.full((1, 8, 1, 1, 1), 0.5))
    assert ChannelAttention(8, reduction=16, dims=2)[0].out_channels == 1  # hidden max(1, C // reduction)


@pytest.mark.parametrize(("cls", "size"), [(SpatialAttention2d, (5, 6)), (SpatialAttention3d, (4, 5, 3))])
def test_spatial_attention_convolves_channel_mean_and_max(cls, size):
    torch.manual_seed(0)
    sa = cls(3)
    assert list(sa.state_dict()) == ["weight"] and sa.bias is None
    x = torch.randn(2, 6, *size)
    pooled = torch.cat([x.mean(1, keepdim=True), x.amax(1, keepdim=True)], 1)
    conv = F.conv2d if len(size) == 2 else F.conv3d
    assert torch.allclose(sa(x), conv(pooled, sa.weight, padding=1), atol=1e-6)
    assert sa(x).shape == (2, 1, *size)
    with pytest.raises(ValueError, match="odd"):
        cls(4)


@pytest.mark.parametrize("dims", [2, 3])
def test_cbam_refines_by_both_maps(dims):
    torch.manual_seed(0)
    block = CBAM(8, reduction=2, spatial_kernel=3, dims=dims)
    assert list(block.state_dict()) == ["channel_mlp.0.weight", "channel_mlp.2.weight", "spatial_conv.weight"]
    x = torch.randn(2, 8, *(4, 5, 3)[:dims])
    out, channel, spatial_logits = block.maps(x)
    assert (
        out.shape == x.shape and channel.shape == (2, 8, *[1] * dims) and spatial_logits.shape == (2, 1, *x.shape[2:])
    )
    attended, channel2, logits2 = cbam(x, block.channel_mlp, block.spatial_conv)
    assert (
        torch.equal(attended, channel * x) and torch.equal(channel2, channel) and torch.equal(logits2, spatial_logits)
    )
    assert torch.equal(block(x), torch.sigmoid(spatial_logits) * (channel * x))
    # zero input: M_c = 1/2, M_s logits 0 (bias-free conv of zeros), so the output is exactly zero
    assert torch.equal(block(torch.zeros_like(x)), torch.zeros_like(x))
    # no spatial preference (zero kernel): sigma(0) = 1/2 everywhere
    nn.init.zeros_(block.spatial_conv.weight)
    assert torch.allclose(block(x), 0.5 * block.channel_mlp(x) * x)
