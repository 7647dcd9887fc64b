"""Building blocks of the metric tests: Batches holding only what metrics read, and random scenes."""

from __future__ import annotations

import torch

from occplug.data.frame import Batch
from occplug.geometry import GridSpec


def make_batch(labels: torch.Tensor, **fields) -> Batch:
    """A Batch of ``labels`` ``(B, X, Y, Z)`` plus any metric-relevant fields (masks, origins...)."""
    b = labels.shape[0]
    return Batch(
        images=torch.zeros(b, 1, 3, 2, 2),
        intrinsics=torch.eye(3).expand(b, 1, 3, 3),
        cam_to_ego=torch.eye(4).expand(b, 1, 4, 4),
        img_aug=torch.eye(3).expand(b, 1, 3, 3),
        ego_to_global=torch.eye(4, dtype=torch.float64).expand(b, 4, 4),
        timestamp=torch.zeros(b, dtype=torch.float64),
        frame_index=torch.zeros(b, dtype=torch.int64),
        has_voxel_labels=torch.ones(b, dtype=torch.bool),
        is_sequence_start=torch.ones(b, dtype=torch.bool),
        scene=["s"] * b,
        token=[f"t{i}" for i in range(b)],
        voxel_labels=labels,
        **fields,
    )


#: A small grid for RayIoU scenes: 16 x 16 x 6 voxels of 0.5 m around the ego.
SMALL_GRID = GridSpec((-4.0, -4.0, -1.0, 4.0, 4.0, 2.0), 0.5)


def random_scene(seed: int, grid: GridSpec = SMALL_GRID, num_classes: int = 5, free: int = 4, density: float = 0.15):
    """``(labels, prediction, origins)``: random labels (``free`` elsewhere), a noisy copy (shifted
    one voxel along x in places, a few classes swapped, a few voxels flipped) and 1-4 origins."""
    gen = torch.Generator().manual_seed(seed)
    shape = grid.shape
    occupied = torch.rand(shape, generator=gen) < density
    occupied[:, :, 0] = True  # a floor, so most downward rays hit
    labels = torch.where(occupied, torch.randint(0, free, shape, generator=gen), free)
    pred = labels.clone()
    half = shape[0] // 2
    pred[half:] = torch.roll(labels, 1, 0)[half:]
    swap = torch.rand(shape, generator=gen) < 0.1
    pred = torch.where(swap & (pred != free), (pred + 1) % free, pred)
    flip = torch.rand(shape, generator=gen) < 0.03
    pred = torch.where(flip, torch.where(pred == free, 0, free), pred)
    n = int(torch.randint(1, 5, (1,), generator=gen))
    lower = torch.tensor(grid.lower, dtype=torch.float64)
    upper = torch.tensor(grid.upper, dtype=torch.float64)
    origins = lower + (upper - lower) * (0.1 + 0.8 * torch.rand(n, 3, generator=gen, dtype=torch.float64))
    return labels, pred, origins.float()
