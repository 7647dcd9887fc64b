"""RayIoU speed on one Occ3D-size sample (200 x 200 x 16 voxels of 0.4 m, 8 origins), on CPU.

The sample is a frame of the synthetic world at the ``occ3d`` preset's grid: ground truth from the
world's voxel labels, origins the LiDAR positions of the scene's 20 frames in that frame's ego
frame (selected as RayIoU does), and a prediction that is the ground truth shifted one voxel along
x with 5 % of its occupied voxels relabelled (the speed depends on how far rays travel, so the
prediction is realistic rather than perfect).

Prints, side by side in one run, RayIoU's seconds per sample with the pure-PyTorch walk (the
reference) and with the compiled walk (numba, when installed), their ratio and the first-use cost of
the compiled one; the pure-PyTorch cast without empty-space skipping; and a per-ray pure-Python Amanatides-Woo reference timed on
``--reference-rays`` random query rays and extrapolated to all rays of the sample (which it also
checks the cast against). ``--json OUT`` writes the timings.
Run: ``python scripts/bench_metrics.py [--threads 1]``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import statistics
import time
from pathlib import Path

import torch

from occplug.data import OCC3D_GRID, Batch
from occplug.data.synthetic import LIDAR_TO_EGO, build_scene, preset, voxel_labels
from occplug.geometry import GridSpec, first_hits, invert_pose
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


def timed(fn, repeats: int) -> tuple[float, list[float]]:
    """``(median, all)`` seconds of ``repeats`` calls of ``fn`` (after one untimed warm-up call)."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--reference-rays", type=int, default=2000)
    parser.add_argument("--json", metavar="OUT", help="also write the timings to this JSON file")
    parser.add_argument(
        "--device", default="cpu", help="also time the pure-PyTorch walk on this device (e.g. cuda; default: CPU only)"
    )
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
    batch = batch_of(labels, sequence)
    record: dict = {"rays": rays, "origins": int(origins.shape[0]), "threads": torch.get_num_threads()}

    def metric_time(kernel: str) -> tuple[float, list[float], float]:
        metric = RayIoU(grid=OCC3D_GRID, kernel=kernel)
        median, times = timed(lambda: metric.update(pred[None], batch), args.repeats)
        metric.reset()
        metric.update(pred[None], batch)
        return median, times, float(metric.compute()["RayIoU"])

    reference, ref_times, ref_score = metric_time("torch")
    line = ", ".join(f"{t:.3f}" for t in ref_times)
    print(f"RayIoU, pure-PyTorch walk (the reference): {reference:.3f} s/sample (median of {args.repeats}: {line})")
    record["torch_s"] = reference
    fast = reference
    if importlib.util.find_spec("numba") is not None:  # what first_hits' kernel 'numba' needs
        start = time.perf_counter()
        first_hits(torch.zeros(1, 2, 2, 2, dtype=torch.bool), GridSpec((0, 0, 0, 2, 2, 2), 1.0),
                   torch.zeros(1, 3), torch.ones(1, 3) / 3**0.5, math.inf, kernel="numba")  # fmt: skip
        first_use = time.perf_counter() - start
        fast, fast_times, fast_score = metric_time("numba")
        line = ", ".join(f"{t:.3f}" for t in fast_times)
        print(
            f"RayIoU, compiled walk (numba): {fast:.3f} s/sample (median of {args.repeats}: {line}); "
            f"its first use in this process (compile or load from numba's cache): {first_use:.2f} s"
        )
        print(
            f"side by side: compiled {fast:.3f} s vs pure PyTorch {reference:.3f} s: ratio {fast / reference:.3f} "
            f"({reference / fast:.1f}x faster); RayIoU {fast_score:.4f} vs {ref_score:.4f} (equal: {fast_score == ref_score})"
        )
        record.update(numba_s=fast, numba_first_use_s=first_use, rayiou=fast_score)
    else:
        print("RayIoU, compiled walk: numba is not installed (pip install occplug[fast]); only the reference ran")

    if args.device != "cpu":
        device = torch.device(args.device)
        metric = RayIoU(grid=OCC3D_GRID, kernel="torch").to(device)
        on_device, device_pred = batch.to(device), pred.to(device)

        def update() -> None:
            metric.update(device_pred[None], on_device)
            if device.type == "cuda":
                torch.cuda.synchronize(device)

        device_time, _ = timed(update, args.repeats)
        metric.reset()
        update()
        score = float(metric.compute()["RayIoU"])
        print(f"RayIoU, pure-PyTorch walk on {device}: {device_time:.3f} s/sample; RayIoU {score:.4f}")
        record.update(device=str(device), device_s=device_time, device_rayiou=score)

    o = origins[:, None].expand(-1, directions.shape[0], 3).reshape(-1, 3)
    d = directions.repeat(origins.shape[0], 1)
    occupied = torch.stack([pred, labels]) != FREE
    start = time.perf_counter()
    first_hits(occupied, OCC3D_GRID, o, d, math.inf, skip=False, kernel="torch")
    plain = time.perf_counter() - start
    print(
        f"pure-PyTorch cast without empty-space skipping: {plain:.3f} s ({plain / reference:.1f}x the reference's time)"
    )

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
        f"{per_sample:.1f} s/sample; {agree}/{len(pick)} rays agree exactly (class, depth within 1e-6 m)"
    )
    print(f"goal <= 1 s/sample: {'met' if fast <= 1 else 'NOT met'} ({fast:.3f} s)")
    if args.json:
        Path(args.json).write_text(json.dumps(record, indent=2) + "\n")


if __name__ == "__main__":
    main()
