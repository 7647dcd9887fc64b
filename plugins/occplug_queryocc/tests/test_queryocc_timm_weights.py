"""``occplug fit -c queryocc/occ3d_nuscenes ... model.encoder.weights=<a timm ConvNeXt file>`` trains a step.

The recipe as shipped, on the tiny synthetic world (queryocc/base's data node and grids, so the world is the
one the plugin's other tests generate), with the recipe's own ConvNeXt-Base and with ConvNeXt-Atto (the same
layout, small), each saved as a user saves it; their ``features_only`` names differ from the file's
(``stem.0`` -> ``stem_0``).
"""

from __future__ import annotations

import json

import pytest
import torch

from occplug.cli import main
from occplug.config import compose


# convnext_base is the recipe's own encoder (the file the README documents); convnext_atto is the same layout, small
@pytest.mark.parametrize("model_name", ["convnext_atto", "convnext_base"])
def test_the_recipe_trains_a_step_from_a_timm_convnext_state_dict(tmp_path, model_name):
    import timm

    torch.manual_seed(0)
    weights = tmp_path / f"{model_name}.pth"
    torch.save(timm.create_model(model_name).state_dict(), weights)  # as a user saves ImageNet weights
    base = compose(["queryocc/base"]).resolved()
    run = tmp_path / "run"
    overrides = [
        "data=" + json.dumps({**base["data"], "preset": "tiny", "batch_size": 1}),
        "grid=" + json.dumps(base["grid"]),
        "model.view_transform.grid=" + json.dumps(base["model"]["view_transform"]["grid"]),
        "model.view_transform.num_bins=8",
        "model.view_transform.depth_far=40.0",
        "model.scene.num_blocks=1",
        "model.heads.occupancy.num_blocks=1",
        f"model.encoder.model_name={model_name}",
        f"model.encoder.weights={weights}",
        "model.supervision.queries.points_per_sample=128",
        "model.supervision.queries.near_range=24.0",
        "model.supervision.queries.sky_rays=32",
        "model.supervision.queries.pixel_stride=4",
        "trainer.precision=32-true",
        "trainer.max_steps=1",
        "trainer.limit_val_batches=0",
    ]
    assert (
        main(["fit", "-c", "queryocc/occ3d_nuscenes", "-c", "occplug/trainer/debug", *overrides, "--run-dir", str(run)])
        == 0
    )
    assert json.loads((run / "metrics.json").read_text())["global_step"] == 1
    state = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)["state_dict"]
    saved = torch.load(weights, map_location="cpu", weights_only=True)
    stem = state["encoder.backbone.stem_0.weight"]
    # one AdamW step (lr 2e-4 scaled to batch 1) moves a weight by about lr; a random init is ~100x further away
    assert (stem - saved["stem.0.weight"]).abs().max() < 1e-3
    assert (stem - timm.create_model(model_name).state_dict()["stem.0.weight"]).abs().max() > 1e-2
