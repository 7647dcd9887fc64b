"""Building blocks of the metric tests: Batches holding only what metrics read, and random scenes."""

from __future__ import annotations

import torch

from occplug.data.frame import Batch
from occplug.geometry import GridSpec
from occplug.testing import label_batch


def make_batch(labels: torch.Tensor, **fields) -> Batch:
    """A Batch of ``labels`` ``(B, X, Y, Z)`` plus any metric-relevant fields (masks, origins...)."""
    return label_batch(labels, **fields)


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
