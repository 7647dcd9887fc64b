"""occplug.nn.layers: conv -> norm -> activation in 2D and 3D."""

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from occplug.nn import ConvNormAct2d, ConvNormAct3d


@pytest.mark.parametrize(("cls", "size"), [(ConvNormAct2d, (7, 6)), (ConvNormAct3d, (5, 4, 3))])
def test_conv_norm_act_is_conv_then_norm_then_activation(cls, size):
    torch.manual_seed(0)
    block = cls(3, 8, 3, norm="group", act="silu").eval()
    assert list(block.state_dict()) == ["0.weight", "1.weight", "1.bias"]  # bias-free conv, GroupNorm
    assert isinstance(block[1], nn.GroupNorm) and block[1].num_groups == 8 and isinstance(block[2], nn.SiLU)
    x = torch.randn(2, 3, *size)
    conv = F.conv2d if len(size) == 2 else F.conv3d
    want = F.silu(F.group_norm(conv(x, block[0].weight, padding=1), 8, block[1].weight, block[1].bias))
    torch.testing.assert_close(block(x), want)
    assert block(x).shape == (2, 8, *size)  # "same" padding


def test_conv_norm_act_defaults_stride_and_bad_activation():
    block = ConvNormAct3d(4, 6, 1)
    assert isinstance(block[1], nn.BatchNorm3d) and isinstance(block[2], nn.ReLU) and block[0].padding == (0, 0, 0)
    assert ConvNormAct2d(3, 4, 3, stride=2)(torch.randn(1, 3, 9, 8)).shape == (1, 4, 5, 4)
    with pytest.raises(ValueError, match="act must be"):
        ConvNormAct3d(4, 6, act="gelu")
