"""Seconds per 3D view (and per camera overlay) of ``occplug viz`` at Occ3D size, on this machine.

The grid is 200 x 200 x 16 voxels of 0.4 m (Occ3D-nuScenes), filled with a seeded procedural
street scene (ground classes, buildings, vehicles, trees, poles),
or with the labels of a file (``--labels FILE``: a ``.npy``/``.npz`` (key ``semantics`` or
``pred``) or ``.pt`` holding an ``(X, Y, Z)`` Occ3D label grid on the same range).

    python scripts/bench_viz.py [--repeat 3] [--size 640x400] [--threads N] [--labels FILE]

Prints one line per measurement: the median and best wall-clock seconds over ``--repeat`` runs
(after one warm-up run) and the process CPU seconds per run.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from occplug.data import OCC3D_CLASSES, OCC3D_FREE
from occplug.geometry import GridSpec
from occplug.viz import Palette, default_view, occupancy_in_cameras, render_voxels

GRID = GridSpec((-40.0, -40.0, -1.0, 40.0, 40.0, 5.4), 0.4)
C = {name: i for i, name in enumerate(OCC3D_CLASSES)}


def street_scene(seed: int = 0) -> torch.Tensor:
    """A ``(200, 200, 16)`` uint8 Occ3D label grid: a crossroads with buildings, cars, trees."""
    gen = np.random.default_rng(seed)
    x, y, _ = GRID.shape
    labels = np.full(GRID.shape, OCC3D_FREE, dtype=np.uint8)
    ii, jj = np.meshgrid(np.arange(x), np.arange(y), indexing="ij")
    road = (np.abs(jj - y // 2) < 18) | (np.abs(ii - x // 2) < 18)
    walk = ~road & ((np.abs(jj - y // 2) < 26) | (np.abs(ii - x // 2) < 26))
    ground = np.where(road, C["driveable_surface"], np.where(walk, C["sidewalk"], C["terrain"]))
    labels[:, :, 0] = ground
    labels[:, :, 1] = np.where(walk, C["sidewalk"], OCC3D_FREE)
    blocks = ~road & ~walk
    for _ in range(24):  # buildings on the blocks
        i0, j0 = gen.integers(0, x - 40), gen.integers(0, y - 40)
        di, dj, h = gen.integers(15, 40), gen.integers(15, 40), gen.integers(6, 16)
        box = np.zeros((x, y), bool)
        box[i0 : i0 + di, j0 : j0 + dj] = True
        labels[box & blocks, 1:h] = C["manmade"]
    for cls, length, width, height, count in (("car", 11, 5, 4, 40), ("truck", 20, 6, 8, 8), ("bus", 28, 7, 9, 4)):
        for _ in range(count):  # vehicles on the roads
            along_x = gen.random() < 0.5
            i0, j0 = gen.integers(0, x - length), gen.integers(0, y - length)
            di, dj = (length, width) if along_x else (width, length)
            if road[i0 : i0 + di, j0 : j0 + dj].all():
                labels[i0 : i0 + di, j0 : j0 + dj, 1 : 1 + height] = C[cls]
    for _ in range(60):  # trees and poles on the sidewalks and terrain
        i0, j0 = gen.integers(2, x - 6), gen.integers(2, y - 6)
        if walk[i0, j0] or (blocks[i0, j0] and labels[i0, j0, 2] == OCC3D_FREE):
            labels[i0 : i0 + 1, j0 : j0 + 1, 1:9] = C["manmade"]
            if gen.random() < 0.6:
                labels[i0 - 2 : i0 + 3, j0 - 2 : j0 + 3, 8:13] = C["vegetation"]
    return torch.from_numpy(labels)


def load_labels(path: Path) -> torch.Tensor:
    if path.suffix == ".pt":
        return torch.load(path, weights_only=True)
    data = np.load(path)
    if isinstance(data, np.lib.npyio.NpzFile):
        key = "semantics" if "semantics" in data else "pred"
        data = data[key]
    return torch.from_numpy(np.asarray(data))


def timed(fn, repeat: int) -> tuple[float, float, float]:
    """Median and best wall seconds and mean CPU seconds of ``repeat`` calls (after a warm-up)."""
    fn()
    walls, cpus = [], []
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return statistics.median(walls), min(walls), statistics.fmean(cpus)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--size", default="640x400", help="3D view size WxH (the panels' default)")
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    parser.add_argument("--labels", type=Path, help="a label grid to render instead of the procedural scene")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    width, height = (int(v) for v in args.size.lower().split("x"))
    labels = load_labels(args.labels) if args.labels else street_scene()
    if tuple(labels.shape) != GRID.shape:
        raise SystemExit(f"--labels: expected a {GRID.shape} grid, got {tuple(labels.shape)}")
    palette = Palette.for_classes(OCC3D_CLASSES, OCC3D_FREE, 255)
    occupied = float(palette.occupied(labels.long()).float().mean())
    print(
        f"grid {GRID.shape[0]}x{GRID.shape[1]}x{GRID.shape[2]} @ {GRID.voxel_size[0]} m, {occupied:.1%} occupied; "
        f"torch {torch.__version__}, {torch.get_num_threads()} threads"
    )
    view = default_view(GRID, width, height)
    med, best, cpu = timed(lambda: render_voxels(labels, GRID, palette, view), args.repeat)
    stats = f"(median of {args.repeat}; best {best:.2f} s; cpu {cpu:.2f} s)"
    print(f"3D view {width}x{height}: {med:.2f} s per view {stats}")
    # six nuScenes-like cameras at the Occ3D preset's image size, as the sample panel casts them
    from occplug.data.synthetic import camera_rig

    _, k, cam_to_ego = camera_rig(6, (256, 704))
    med, best, cpu = timed(lambda: occupancy_in_cameras(labels, GRID, palette, k, cam_to_ego, (256, 704)), args.repeat)
    stats = f"(median of {args.repeat}; best {best:.2f} s; cpu {cpu:.2f} s)"
    print(f"camera overlays 6x704x256: {med:.2f} s per sample {stats}")


if __name__ == "__main__":
    main()
