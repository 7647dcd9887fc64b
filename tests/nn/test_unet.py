"""occplug.nn's dense UNets: anisotropic downsampling, shapes on odd sizes, the per-cell header."""

import pytest
import torch

from occplug.nn import UNet2d, UNet3d, halving_stride


def test_halving_stride_halves_only_axes_that_keep_min_size_cells():
    assert halving_stride((64, 64, 8), 2) == (2, 2, 2)
    assert halving_stride((8, 8, 3), 2) == (2, 2, 1)  # 3 < 2 * 2: z keeps stride 1
    assert halving_stride((4, 3), 2) == (2, 1)
    assert halving_stride((5, 1), 1) == (2, 1)


@pytest.mark.parametrize(
    ("shape", "bottleneck"), [((64, 64, 8), (8, 8, 2)), ((32, 32, 4), (4, 4, 2)), ((9, 7, 3), (3, 2, 3))]
)
def test_unet3d_keeps_anisotropic_grid_shapes(shape, bottleneck):
    net = UNet3d(in_channels=16, num_classes=5, base_channels=4, depth=3)
    seen = []
    net.down[-1].register_forward_hook(lambda _m, _i, out: seen.append(tuple(out.shape[2:])))
    out = net(torch.randn(1, 16, *shape))
    assert out.shape == (1, 5, *shape)
    assert seen == [bottleneck]  # an axis stops halving once it would drop below min_size = 2 cells
    assert net.features(torch.randn(1, 16, *shape)).shape == (1, 4, *shape)


def test_unet2d_shapes_on_odd_images():
    net = UNet2d(in_channels=3, num_classes=7, base_channels=8, depth=3)
    assert net(torch.randn(2, 3, 37, 50)).shape == (2, 7, 37, 50)


def test_unet_header_is_a_1x1_conv_of_the_features():
    torch.manual_seed(0)
    net = UNet2d(in_channels=3, num_classes=4, base_channels=8, depth=1).eval()
    x = torch.randn(1, 3, 12, 10)
    feats = net.features(x)
    assert feats.shape == (1, 8, 12, 10)
    torch.testing.assert_close(net(x), torch.nn.functional.conv2d(feats, net.head.weight, net.head.bias))


def test_unet_depth_zero_is_stem_and_header():
    net = UNet3d(in_channels=2, num_classes=3, base_channels=4, depth=0)
    assert len(net.down) == 0 and len(net.up) == 0
    assert net(torch.randn(1, 2, 3, 4, 5)).shape == (1, 3, 3, 4, 5)


def test_unet_rejects_bad_arguments_and_inputs():
    with pytest.raises(ValueError, match="depth must be >= 0"):
        UNet2d(depth=-1)
    with pytest.raises(ValueError, match="must be >= 1"):
        UNet3d(in_channels=0)
    with pytest.raises(ValueError, match="expects a 5-D input"):
        UNet3d(in_channels=2)(torch.randn(1, 2, 4, 4))
