"""Metrics give identical results sharded over two gloo processes and in one process."""

import socket

import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from metric_batches import SMALL_GRID, make_batch, random_scene

from occplug.metrics import Occ3DMIoU, RayIoU, SSCMetrics

SAMPLES = 5  # odd: the ranks get 3 and 2 samples


def build_metrics():
    return {
        "occ3d_miou": Occ3DMIoU(num_classes=5, free_label=4, mask="camera"),
        "rayiou": RayIoU(num_classes=5, free_label=4, grid=SMALL_GRID),
        "ssc": SSCMetrics(num_classes=5, free_label=4),
    }


def sample(i):
    labels, pred, origins = random_scene(100 + i)
    gen = torch.Generator().manual_seed(i)
    camera = torch.rand(labels.shape, generator=gen) < 0.7
    invalid = torch.rand(labels.shape, generator=gen) < 0.1
    labels = torch.where(torch.rand(labels.shape, generator=gen) < 0.02, 255, labels)  # some ignored voxels
    batch = make_batch(
        labels[None], mask_camera=camera[None], voxel_invalid=invalid[None], sequence_lidar_origins=[origins]
    )
    return pred[None], batch


def evaluate(indices):
    metrics = build_metrics()
    for i in indices:
        pred, batch = sample(i)
        for m in metrics.values():
            m.update(pred, batch)
    return {name: m.compute() for name, m in metrics.items()}


def worker(rank, world, port, out):
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=world)
    try:
        results = evaluate(range(rank, SAMPLES, world))  # compute() all-reduces the count states
        torch.save(results, f"{out}/rank{rank}.pt")
    finally:
        dist.destroy_process_group()


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_gloo_processes_equal_one_process(tmp_path):
    single = evaluate(range(SAMPLES))
    mp.spawn(worker, args=(2, free_port(), str(tmp_path)), nprocs=2, join=True)
    for rank in range(2):
        sharded = torch.load(tmp_path / f"rank{rank}.pt", weights_only=True)
        assert sharded.keys() == single.keys()
        for name, values in single.items():
            assert sharded[name].keys() == values.keys()
            for key, value in values.items():
                torch.testing.assert_close(
                    sharded[name][key], value, rtol=0, atol=0, equal_nan=True, msg=f"{name} {key}"
                )
    assert single["rayiou"]["RayIoU"] > 0 and single["ssc"]["mIoU"] > 0 and single["occ3d_miou"]["mIoU"] > 0
    shard = evaluate(range(1, SAMPLES, 2))  # one rank's samples alone score differently: the sync mattered
    assert all(
        not torch.equal(shard[name][key], single[name][key])
        for name, key in (("occ3d_miou", "mIoU"), ("rayiou", "RayIoU"), ("ssc", "mIoU"))
    )
