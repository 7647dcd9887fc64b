"""``occplug/model/baseline``: the core's model base config; recipes layer on it and change one slot."""

from __future__ import annotations

import copy
import importlib
from pathlib import Path

from occplug.config import compose

ROOT = Path(__file__).resolve().parents[2]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
MODEL_BASE = (ROOT / "occplug" / "configs" / "model" / "baseline.yaml").resolve()

# configs/baseline.yaml as it was before its model node moved into occplug/model/baseline (the reference).
FLAT_BASELINE = """\
base: [occplug/trainer/default, occplug/data/synthetic]
seed: 0
grid: {range: [-24.0, -24.0, -1.0, 24.0, 24.0, 5.4], voxel_size: 0.8}
model:
  type: occ_model
  encoder: {type: small_cnn, out_channels: 64, stride: 8}
  view_transform: {type: lss, out_channels: 32, depth_bins: [1.0, 40.0, 1.0]}
  scene: {type: dense_voxels, out_channels: 32, num_blocks: 1}
  heads:
    occupancy: {type: voxel_classifier, hidden: 64}
  supervision:
    voxel_labels: {type: voxel_ce, camera_mask: true}
optimizer: {type: adamw, lr: 0.002, weight_decay: 0.01}
scheduler: {type: cosine, warmup_steps: 50}
metrics: [occ3d_miou]
trainer: {max_epochs: 13}
"""


def test_layered_baseline_resolves_exactly_as_the_flat_one(tmp_path):
    flat = tmp_path / "flat.yaml"
    flat.write_text(FLAT_BASELINE)
    layered = compose([BASELINE])
    assert layered.resolved() == compose([str(flat)]).resolved()
    assert MODEL_BASE in [p.resolve() for p in layered.files]
    assert Path(layered.sources["model.heads.occupancy.type"]).resolve() == MODEL_BASE
    assert "grid" not in layered.resolved()["model"]["view_transform"]  # the model gives it the top-level grid


def test_the_example_recipe_changes_only_the_occupancy_head(monkeypatch, isolated_registry):
    monkeypatch.syspath_prepend(str(ROOT / "plugins" / "example" / "src"))
    isolated_registry(plugins=[("example", importlib.import_module("occplug_example.plugin"))])
    recipe = compose(["example/tiny"])
    model = recipe.resolved()["model"]
    expected = copy.deepcopy(compose([BASELINE]).resolved()["model"])
    expected["heads"]["occupancy"] = {"type": "tiny_mlp", "hidden": 16}
    assert model == expected
    assert Path(recipe.sources["model.encoder.type"]).resolve() == MODEL_BASE
    assert recipe.sources["model.heads.occupancy.type"].endswith("tiny.yaml")
