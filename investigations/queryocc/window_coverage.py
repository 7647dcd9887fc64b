"""How much does QueryOcc's temporal window add to what the metrics score? (No training: data only.)

For validation samples of ``queryocc/base``'s world, the pseudo points (pseudo depth + pseudo semantics, every 2nd
pixel, free-labelled points dropped) of the current frame and of the adjacent frames t-1 and t+1 (moved into the
current ego frame, as the query source does) are voxelised on the evaluation grid. Printed: per frame offset, the
share of points inside the grid and inside the current frame's camera mask, and how many occupied camera-visible
voxels (what Sem./Occ. IoU and RayIoU score) the adjacent frames reach that the current frame's points miss.

    python investigations/queryocc/window_coverage.py [--batches 6]
"""

from __future__ import annotations

import argparse

import torch

from occplug.run.runner import build_datamodule, load_config
from occplug_queryocc.supervision import supervision_points


def main() -> None:
    parser = argparse.ArgumentParser(
        prog="python investigations/queryocc/window_coverage.py",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--batches", type=int, default=6)
    args = parser.parse_args()
    dm = build_datamodule(load_config(["queryocc/base"], []))
    dm.prepare_data()
    dm.setup("fit")
    grid, shape = dm.grid, torch.tensor(dm.grid.shape)
    points = {k: [0, 0, 0] for k in (-1, 0, 1)}  # points, inside the grid, inside the camera mask
    scored = hit_now = added = 0
    for i, batch in enumerate(dm.val_dataloader()):
        if i >= args.batches:
            break
        hits = {}
        for k in (0, -1, 1):
            for b, (pts, _) in enumerate(supervision_points(batch, "pseudo", [k], 255, 2)):
                p = pts.points[pts.labels != dm.free_label]
                idx = grid.coord_to_index(p).long()
                inside = ((idx >= 0) & (idx < shape)).all(-1)
                idx = idx[inside]
                vox = torch.zeros(grid.shape, dtype=torch.bool)
                vox[idx[:, 0], idx[:, 1], idx[:, 2]] = True
                points[k][0] += len(p)
                points[k][1] += int(inside.sum())
                points[k][2] += int(batch.mask_camera[b][idx[:, 0], idx[:, 1], idx[:, 2]].sum())
                hits[(k, b)] = vox
        for b in range(len(batch)):
            labels = batch.voxel_labels[b]
            target = (labels != dm.free_label) & (labels != 255) & batch.mask_camera[b]
            scored += int(target.sum())
            hit_now += int((hits[(0, b)] & target).sum())
            added += int(((hits[(-1, b)] | hits[(1, b)]) & target & ~hits[(0, b)]).sum())
    for k, (n, in_grid, in_cam) in points.items():
        print(f"offset {k:+d}: {n} points; {in_grid / n:.1%} inside the grid; {in_cam / n:.1%} in the camera mask")
    print(
        f"occupied camera-visible voxels: {scored}; reached by the current frame: {hit_now} ({hit_now / scored:.1%}); "
        f"reached only by t-1 / t+1: {added} ({added / scored:.1%})"
    )


if __name__ == "__main__":
    main()
