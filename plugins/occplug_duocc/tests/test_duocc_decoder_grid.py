"""duocc_decoder takes its grid from the run and its upsampling from the scene's downsample: one value each."""

from __future__ import annotations

import pytest
from torch import nn

from occplug.config import ConfigError
from occplug.geometry import GridSpec
from occplug.plugins import get_registry
from occplug.run import runner

DEBUG = "occplug/trainer/debug"
SMALL = ["grid.range=[-8.0,-8.0,-1.0,8.0,8.0,5.4]", "model.encoder.width=16"]
NODE = {"range": [-8.0, -8.0, -1.0, 8.0, 8.0, 5.4], "voxel_size": 0.8}


def test_the_decoder_upsamples_by_the_scene_s_downsample_onto_the_given_grid():
    head = get_registry().build(
        "head", {"type": "duocc_decoder"}, in_channels=8, num_classes=5, grid=NODE, scene_downsample=2
    )
    assert head.grid == GridSpec.from_config(NODE) and isinstance(head.grid, GridSpec)
    deconv = head.up[0]
    assert isinstance(deconv, nn.ConvTranspose3d) and deconv.stride == (2, 2, 2)
    flat = get_registry().build("head", "duocc_decoder", in_channels=8, num_classes=5, grid=NODE, scene_downsample=1)
    assert isinstance(flat.up[0], nn.Conv3d) and flat.up[0].kernel_size == (1, 1, 1)
    with pytest.raises(ValueError, match=r"^duocc_decoder: the scene downsamples the grid by 3; the decoder upsamples"):
        get_registry().build("head", "duocc_decoder", in_channels=8, num_classes=5, grid=NODE, scene_downsample=3)


@pytest.mark.parametrize("downsample", [1, 2])
def test_in_a_run_the_scene_s_downsample_is_the_one_value(downsample):
    cfg = runner.load_config(["duocc/stream_agg", DEBUG], [*SMALL, f"model.scene.downsample={downsample}"])
    _, model = runner.build_run(cfg)
    head = model.heads["occupancy"]
    assert head.scale == model.scene.downsample == downsample
    assert head.grid == model.grid == model.context.grid


def test_a_config_that_still_sets_the_decoder_s_scale_is_one_error():
    with pytest.raises(ConfigError, match=r"model\.heads\.occupancy\.scale"):
        runner.load_config(["duocc/stream_agg", DEBUG], [*SMALL, "model.heads.occupancy.scale=2"])
