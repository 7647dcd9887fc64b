"""Fixtures shared by the DuOcc tests."""

import pytest
import torch

from occplug.run import runner

#: the tiny world on a 16 m grid with narrow image features: the recipes shrunk for test speed
SMALL_FULL = ["grid.range=[-8.0,-8.0,-1.0,8.0,8.0,5.4]", "model.encoder.out_channels=16", "model.encoder.width=16"]


@pytest.fixture(scope="module")
def model_dm():
    """``(model, data module)`` of ``duocc/full`` on the tiny world (random weights), one per test module."""
    torch.manual_seed(0)
    cfg = runner.load_config(["duocc/full", "occplug/trainer/debug"], ["data.preset=tiny", *SMALL_FULL])
    dm, model = runner.build_run(cfg)
    return model, dm
