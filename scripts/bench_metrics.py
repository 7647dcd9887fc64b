"""RayIoU speed on one Occ3D-size sample (200 x 200 x 16 voxels of 0.4 m, 8 origins), on CPU.

The sample is a frame of the synthetic world at the ``occ3d`` preset's grid: ground truth from the
world's voxel labels, origins the LiDAR positions of the scene's 20 frames in that frame's ego
frame (selected as RayIoU does), and a prediction that is the ground truth shifted one voxel along
x with 5 % of its occupied voxels relabelled (the speed depends on how far rays travel, so the
prediction is realistic rather than perfect).

Prints the vectorised metric's seconds per sample (median of ``--repeats``), the same cast without
empty-space skipping, and a per-ray pure-Python Amanatides-Woo reference timed on
``--reference-rays`` random query rays and extrapolated to all rays of the sample (which it also
checks the vectorised cast against). Run: ``python scripts/bench_metrics.py [--threads 2]``.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import torch

from occplug.data import OCC3D_GRID, Batch
from occplug.data.synthetic import LIDAR_TO_EGO, build_scene, preset, voxel_labels
from occplug.geometry import first_hits, invert_pose
from occplug.metrics import RayIoU, cast_query_rays, query_ray_directions, select_origins

FREE = 17


def occ3d_sample(frame: int = 10) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(labels, prediction, sequence origins)`` of one ``occ3d``-preset frame."""
    config = preset("occ3d")
    scene = build_scene(config, "val", 0)
    ego_to_world = scene.ego_to_world(frame / config.fps)
    world_to_ego = invert_pose(ego_to_world)
    prims = scene.primitives_at(frame / config.fps).transformed(world_to_ego)
    labels = voxel_labels(prims, scene.ground, ego_to_world, config.grid, config.label_subsamples).long()
    lidar = torch.cat([LIDAR_TO_EGO[:3, 3].double(), torch.ones(1, dtype=torch.float64)])
    origins = torch.stack(
        [(world_to_ego @ scene.ego_to_world(k / config.fps) @ lidar)[:3] for k in range(config.frames("val"))]
    ).float()
    gen = torch.Generator().manual_seed(0)
    pred = torch.roll(labels, 1, 0)
    relabel = (torch.rand(labels.shape, generator=gen) < 0.05) & (pred != FREE)
    pred = torch.where(relabel, torch.randint(0, FREE, labels.shape, generator=gen), pred)
    return labels, pred, origins


def batch_of(labels: torch.Tensor, origins: torch.Tensor) -> Batch:
    return Batch(
        images=torch.zeros(1, 0, 3, 1, 1),
        intrinsics=torch.zeros(1, 0, 3, 3),
        cam_to_ego=torch.zeros(1, 0, 4, 4),
        img_aug=torch.zeros(1, 0, 3, 3),
        ego_to_global=torch.eye(4, dtype=torch.float64)[None],
        timestamp=torch.zeros(1, dtype=torch.float64),
        frame_index=torch.zeros(1, dtype=torch.int64),
        has_voxel_labels=torch.ones(1, dtype=torch.bool),
        is_sequence_start=torch.ones(1, dtype=torch.bool),
        scene=["s"],
        token=["t"],
        voxel_labels=labels[None],
        sequence_lidar_origins=[origins],
    )


def reference_ray(labels: list, shape, lower, size, origin, direction) -> tuple[int, float]:
    """Per-ray Amanatides-Woo in pure Python: (class, exit depth) of the first occupied voxel."""
    g = [(origin[a] - lower[a]) / size for a in range(3)]
    voxel = [math.floor(v) for v in g]
    step = [1 if d > 0 else -1 for d in direction]
    t_max = [((voxel[a] + (step[a] > 0)) - g[a]) * size / direction[a] if direction[a] else math.inf for a in range(3)]
    t_delta = [size / abs(direction[a]) if direction[a] else math.inf for a in range(3)]
    while all(0 <= voxel[a] < shape[a] for a in range(3)):
        a = min(range(3), key=t_max.__getitem__)
        cls = labels[voxel[0]][voxel[1]][voxel[2]]
        if cls != FREE:
            return cls, t_max[a]
        voxel[a] += step[a]
        t_max[a] += t_delta[a]
    return FREE, math.inf


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--reference-rays", type=int, default=2000)
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    labels, pred, sequence = occ3d_sample()
    origins = select_origins(sequence)
    directions = query_ray_directions()
    rays = origins.shape[0] * directions.shape[0]
    print(
        f"sample: {tuple(labels.shape)} voxels of {OCC3D_GRID.voxel_size[0]} m, {origins.shape[0]} origins "
        f"(of {sequence.shape[0]}), {rays} query rays, each cast through prediction and ground truth; "
        f"torch threads: {torch.get_num_threads()}"
    )

    metric = RayIoU(grid=OCC3D_GRID)
    batch = batch_of(labels, sequence)
    metric.update(pred[None], batch)  # warm-up
    times = []
    for _ in range(args.repeats):
        start = time.perf_counter()
        metric.update(pred[None], batch)
        times.append(time.perf_counter() - start)
    fast = statistics.median(times)
    print(
        f"RayIoU (vectorised, empty-space skipping): {fast:.3f} s/sample (median of {args.repeats}: "
        + ", ".join(f"{t:.3f}" for t in times)
        + f"); RayIoU of this prediction {metric.compute()['RayIoU']:.2f}"
    )

    o = origins[:, None].expand(-1, directions.shape[0], 3).reshape(-1, 3)
    d = directions.repeat(origins.shape[0], 1)
    occupied = torch.stack([pred, labels]) != FREE
    start = time.perf_counter()
    first_hits(occupied, OCC3D_GRID, o, d, math.inf, skip=False)
    plain = time.perf_counter() - start
    print(f"same cast without skipping: {plain:.3f} s ({plain / fast:.1f}x the metric's time)")

    pick = torch.randperm(rays, generator=torch.Generator().manual_seed(0))[: args.reference_rays]
    cast = cast_query_rays(pred, labels, OCC3D_GRID, origins, FREE, directions)
    lists = pred.tolist(), labels.tolist()
    lower, size = OCC3D_GRID.lower, OCC3D_GRID.voxel_size[0]
    start = time.perf_counter()
    results = [
        [reference_ray(grid, labels.shape, lower, size, o[r].tolist(), d[r].tolist()) for grid in lists]
        for r in pick.tolist()
    ]
    spent = time.perf_counter() - start
    per_sample = spent / len(pick) * rays
    agree = sum(
        (
            p[0] == int(cast.pred_class[r])
            and g[0] == int(cast.gt_class[r])
            and math.isclose(p[1], float(cast.pred_depth[r]), abs_tol=1e-6)
            and math.isclose(g[1], float(cast.gt_depth[r]), abs_tol=1e-6)
        )
        for (p, g), r in zip(results, pick.tolist(), strict=True)
    )
    print(
        f"per-ray Python reference: {spent:.2f} s for {len(pick)} random rays x 2 grids, extrapolated to "
        f"{per_sample:.1f} s/sample; vectorised speed-up {per_sample / fast:.0f}x; "
        f"{agree}/{len(pick)} rays agree exactly (class, depth within 1e-6 m)"
    )
    print(f"goal < 1 s/sample: {'met' if fast < 1 else 'NOT met'}")


if __name__ == "__main__":
    main()
