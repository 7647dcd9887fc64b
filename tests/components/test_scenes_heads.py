"""Dense voxel scene and voxel classifier: sampling, querying and the chunked query default agree with the dense path."""

from __future__ import annotations

import pytest
import torch

from occplug.components import DenseVoxels, DenseVoxelScene, VoxelClassifier
from occplug.geometry import GridSpec
from occplug.interfaces import Lifted, OccupancyHead

GRID = GridSpec(range=(-2.0, -1.6, -0.4, 2.0, 1.6, 1.2), voxel_size=0.4)  # (10, 8, 4)


def _centers(grid: GridSpec, b: int) -> torch.Tensor:
    return grid.centers().reshape(1, -1, 3).expand(b, -1, -1)


def test_dense_voxels_shape_and_sample_at_voxel_centres() -> None:
    torch.manual_seed(0)
    rep = DenseVoxels(in_channels=3, out_channels=6, num_blocks=2)
    lifted = Lifted(volume=torch.randn(2, 3, *GRID.shape), grid=GRID)
    scene = rep(lifted, batch=None)  # type: ignore[arg-type]  # stateless: the batch is unused
    assert isinstance(scene, DenseVoxelScene)
    assert scene.features.shape == (2, 6, *GRID.shape) and scene.grid == GRID and scene.channels == 6
    assert scene.batch_size == 2 and scene.device == torch.device("cpu")
    read = scene.sample(_centers(GRID, 2))  # (B, P, C)
    torch.testing.assert_close(read, scene.features.flatten(2).transpose(1, 2), atol=1e-5, rtol=1e-5)
    # halfway between two voxel centres along x: their mean; outside the grid: zero
    mid = torch.tensor([[[-1.6, -1.4, -0.2], [5.0, 0.0, 0.0]]]).expand(2, -1, -1)
    out = scene.sample(mid)
    torch.testing.assert_close(out[:, 0], scene.features[:, :, :2, 0, 0].mean(-1), atol=1e-5, rtol=1e-5)
    assert torch.all(out[:, 1] == 0)
    scene.features.sum().backward()
    assert all(p.grad is not None for p in rep.parameters())


def test_dense_voxels_rejects_bev_volumes() -> None:
    rep = DenseVoxels(in_channels=3)
    with pytest.raises(ValueError, match="needs a 3D volume .* BEV volume"):
        rep(Lifted(volume=torch.zeros(1, 3, 10, 8), grid=GRID), batch=None)  # type: ignore[arg-type]


def test_voxel_classifier_query_matches_dense_logits() -> None:
    torch.manual_seed(0)
    head = VoxelClassifier(in_channels=6, num_classes=5, hidden=16)
    scene = DenseVoxelScene(torch.randn(2, 6, *GRID.shape), GRID)
    logits = head(scene, batch=None)["logits"]  # type: ignore[arg-type]
    assert logits.shape == (2, 5, *GRID.shape)
    result = head.query(scene, _centers(GRID, 2))
    assert result.class_logits.shape == (2, GRID.shape[0] * GRID.shape[1] * GRID.shape[2], 5)
    assert result.occupancy_logit is None and result.features is None  # free is one of its K classes
    torch.testing.assert_close(result.class_logits, logits.flatten(2).transpose(1, 2), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(head.occupancy_logits(scene, GRID), logits, rtol=0, atol=0)
    assert head.queryable and not head.temporal


def test_voxel_classifier_fast_path_equals_the_query_default() -> None:
    """On its own dense grid the head classifies the volume directly; the base class's chunked query
    default (trilinear reads at the centres) gives the same logits, in training too (gradients agree)."""
    torch.manual_seed(0)
    head = VoxelClassifier(in_channels=6, num_classes=5, hidden=16)
    features = torch.randn(2, 6, *GRID.shape, requires_grad=True)
    scene = DenseVoxelScene(features, GRID)
    fast = head.occupancy_logits(scene, GRID)
    default = OccupancyHead.occupancy_logits(head, scene, GRID, chunk_size=37)
    torch.testing.assert_close(default, fast, atol=1e-5, rtol=1e-5)
    (grad_fast,) = torch.autograd.grad(fast.square().sum(), features)
    (grad_default,) = torch.autograd.grad(default.square().sum(), features)
    torch.testing.assert_close(grad_default, grad_fast, atol=1e-4, rtol=1e-4)


def test_voxel_classifier_on_another_grid_queries_its_centres() -> None:
    torch.manual_seed(0)
    head = VoxelClassifier(in_channels=4, num_classes=3, hidden=0)
    scene = DenseVoxelScene(torch.randn(1, 4, *GRID.shape), GRID)
    coarse = GridSpec(range=(-1.6, -1.6, -0.4, 1.6, 1.6, 1.2), voxel_size=0.8)  # centres midway between fine ones
    out = head.occupancy_logits(scene, coarse)
    assert out.shape == (1, 3, *coarse.shape)
    expected = head.query(scene, _centers(coarse, 1)).class_logits.transpose(1, 2).reshape(out.shape)
    torch.testing.assert_close(out, expected)
    # a linear head commutes with trilinear sampling: a coarse centre's logits = mean of its 8 fine voxels' logits
    fine = head(scene, batch=None)["logits"]  # type: ignore[arg-type]
    torch.testing.assert_close(out[0, :, 0, 0, 0], fine[0, :, 1:3, 0:2, 0:2].mean(dim=(1, 2, 3)), atol=1e-5, rtol=1e-5)
