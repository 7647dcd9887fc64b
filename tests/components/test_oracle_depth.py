"""oracle_depth: the perfect-depth depth net lifts every feature cell to the bin of its true depth."""

from __future__ import annotations

import pytest
import torch

from occplug.components import LSSViewTransform, OracleDepthNet
from occplug.components.depth_nets import oracle_depth_logits
from occplug.components.view_transforms import depth_bin_centers
from occplug.geometry import GridSpec
from occplug.testing import check_component, hand_batch, make_tiny_batch
from occplug.testing.conformance import tiny_context

UNIFORM = depth_bin_centers([1.0, 45.0, 1.0])  # 44 bins, centres 1.5 .. 44.5


def test_logits_are_one_hot_at_the_true_depth_bin():
    depth = torch.zeros(1, 1, 4, 8)
    depth[..., 0:2, 0:2] = 3.7  # cell (0, 0) at stride 2 reads pixel (1, 1)
    depth[..., 1, 3] = 44.99  # cell (0, 1): the last bin
    depth[..., 3, 5] = 1.0  # cell (1, 2): the first bin's lower edge
    depth[..., 3, 7] = 45.0  # cell (1, 3): beyond the last bin -> uniform
    logits = oracle_depth_logits(depth, 2, 4, UNIFORM)
    probs = logits.softmax(dim=2)
    assert logits.shape == (1, 1, 44, 2, 4)
    assert probs[0, 0, 2, 0, 0] == 1.0 and probs[0, 0, :, 0, 0].sum() == 1.0  # floor(3.7 - 1) = 2, exactly one-hot
    assert probs[0, 0, 43, 0, 1] == 1.0
    assert probs[0, 0, 0, 1, 2] == 1.0
    assert torch.allclose(probs[0, 0, :, 1, 3], torch.full((44,), 1 / 44))  # out of range
    assert torch.allclose(probs[0, 0, :, 1, 0], torch.full((44,), 1 / 44))  # no depth (sky)


def test_uneven_bins_take_the_nearest_centre():
    centres = torch.tensor([1.0, 2.0, 4.0, 8.0])
    depth = torch.tensor([2.9, 3.1, 5.9, 6.1, 0.4, 10.5]).view(1, 1, 1, 6)
    index = oracle_depth_logits(depth, 1, 6, centres).argmax(2).flatten().tolist()
    assert index[:4] == [1, 2, 2, 3]
    logits = oracle_depth_logits(depth, 1, 6, centres)
    assert (logits[..., 4:] == 0).all()  # 0.4 < 1 - 0.5 and 10.5 >= 8 + 2: uniform


def test_lss_with_the_oracle_lifts_onto_the_true_depth():
    batch = make_tiny_batch(1)
    vt = LSSViewTransform(
        in_channels=8,
        image_stride=4,
        grid=GridSpec.from_config(batch_grid()),
        out_channels=4,
        depth_bins=[1.0, 41.0, 2.0],
        depth_net={"type": "oracle_depth", "hidden": 0},
        context=tiny_context(GridSpec.from_config(batch_grid())),  # the depth-net node is built through the run context
    )
    assert isinstance(vt.depth_net, OracleDepthNet)
    assert torch.equal(vt.depth_net.centers, vt.depth_centers)  # lss filled in its own bins
    h, w = batch.images.shape[-2] // 4, batch.images.shape[-1] // 4
    out = vt(torch.randn(1, batch.images.shape[1], 8, h, w), batch)
    z = batch.depth[..., 2::4, 2::4]
    valid = (z >= 1.0) & (z < 41.0)
    best = out.depth_probs.argmax(2)
    assert valid.any()
    assert torch.equal(best[valid], torch.floor((z[valid] - 1.0) / 2.0).long())
    assert (out.depth_probs.amax(2)[valid] == 1.0).all()


def batch_grid():
    from occplug.data.synthetic import preset

    return preset("tiny").grid.to_dict()


def test_bins_must_match_and_depth_must_be_there():
    with pytest.raises(ValueError, match="oracle_depth"):
        OracleDepthNet(8, 10, 4, depth_bins=[1.0, 45.0, 1.0])
    net = OracleDepthNet(8, 44, 4, depth_bins=[1.0, 45.0, 1.0])
    assert torch.allclose(net.centers, UNIFORM)
    batch = hand_batch(1, images=torch.rand(1, 1, 3, 8, 8))
    with pytest.raises(ValueError, match="true depth maps"):
        net(torch.randn(1, 1, 8, 2, 2), batch)


def test_oracle_depth_conforms():
    check_component("depth_net", "oracle_depth", batch=make_tiny_batch())
