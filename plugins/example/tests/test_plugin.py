"""Tests a plugin author writes: registration via the installed entry point, conformance, a short fit."""

import json

import pytest

from occplug.testing import check_component, make_tiny_batch, run_config


def test_entry_point_registers_the_head(isolated_registry):
    registry = isolated_registry(entry_points=["example"])  # fails if pyproject lacks the entry point
    entry = registry.get("head", "tiny_mlp")
    assert entry.plugin == "example" and entry.distribution == "occplug-example"


@pytest.mark.parametrize("hidden", [8, 32])
def test_tiny_mlp_conforms(isolated_registry, hidden):
    isolated_registry(entry_points=["example"])
    check_component("head", "tiny_mlp", {"hidden": hidden}, batch=make_tiny_batch())


def test_shipped_config_trains(isolated_registry, tmp_path):
    isolated_registry(entry_points=["example"])
    metrics = run_config("example/tiny", run_dir=tmp_path / "run")
    assert "mIoU" in metrics
    assert "mIoU" in json.loads((tmp_path / "run" / "metrics.json").read_text())


def test_tiny_mlp_voxel_logits_are_the_core_query_default(isolated_registry):
    """The head implements only `query`; its voxel logits (the core's chunked default) are its MLP applied to
    each voxel's own features, and it answers the current frame only."""
    import torch

    import occplug
    from occplug.components import DenseVoxelScene

    registry = isolated_registry(entry_points=["example"])
    head = registry.build("head", {"type": "tiny_mlp", "hidden": 8}, in_channels=4, num_classes=5)
    assert head.queryable and not head.temporal
    grid = occplug.GridSpec(range=(-2.0, -2.0, 0.0, 2.0, 2.0, 0.8), voxel_size=0.4)
    scene = DenseVoxelScene(torch.randn(2, 4, *grid.shape, generator=torch.Generator().manual_seed(0)), grid)
    with torch.no_grad():
        logits = head.occupancy_logits(scene, grid, chunk_size=33)
        dense = head.mlp(scene.features.movedim(1, -1)).movedim(-1, 1)
        torch.testing.assert_close(logits, dense, atol=1e-5, rtol=1e-5)
        points = grid.centers().reshape(1, -1, 3).expand(2, -1, -1)
        with pytest.raises(ValueError, match="not temporal"):
            head.query(scene, points, torch.full(points.shape[:2], -0.5))
