#!/usr/bin/env python
"""Benchmark the splat at a nuScenes-like size: naive vs fast splat (outer product, per point) vs backward projection.

Size (defaults): 6 cameras of the synthetic world's nuScenes-like rig at 256 x 704 pixels, stride 16
(16 x 44 feature maps), 88 depth bins ([1, 45) m in 0.5 m steps), 64 channels, the Occ3D grid
(200 x 200 x 16 voxels of 0.4 m over [-40, 40] x [-40, 40] x [-1, 5.4] m), batch 1.

Measured, each on the same inputs and output layout (a contiguous ``(B, C, X, Y, Z)`` float32 volume):

* ``naive``: the reference LSS splat: the ``(B, N, D, h, w, C)`` depth x context products, made
  channels-last, ``index_add_`` over all frustum points (:func:`occplug.components.splat`), then
  the channels-first volume. The frustum voxel index is precomputed, i.e. *not* timed here
  (the reference LSS recomputes it every forward: the ``geometry`` line).
* ``fast``: :func:`occplug.ops.splat_outer` with a cached :class:`occplug.ops.SplatPlan`
  (its one-off build per geometry is the ``plan build`` line).
* ``naive_points`` / ``fast_points``: the per-point path, arbitrary ``(B, N, D, C, h, w)`` features
  (here the same products, materialised): ``index_add_`` over all points vs
  :func:`occplug.ops.splat_points` with the same cached plans.
* ``backward_projection``: the whole :class:`~occplug.components.BackwardProjection` module
  (1x1 projection, projection of every voxel centre into every camera, bilinear sampling, mean).

Times are wall-clock milliseconds (median and best of ``--repeat`` runs after a warm-up);
forward+backward back-propagates a fixed random gradient of the volume. Peak memory is the peak
resident set size above the level before the call (Linux: ``/proc/self/clear_refs`` resets the
high-water mark, ``VmHWM`` reads it), i.e. every tensor the call allocates, including the
output volume (here 164 MB) and autograd's saved tensors. The last lines are the ratios naive / fast of both paths.

Usage: ``python scripts/bench_view_transform.py [--repeat 5] [--batch 1] [--threads N]``
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch

from occplug.components import BackwardProjection, depth_bin_centers
from occplug.data.synthetic import camera_rig
from occplug.geometry import GridSpec
from occplug.ops import FrustumSplatter, splat, splat_outer, splat_points

IMAGE_SIZE = (256, 704)
STRIDE = 16
DEPTH_BINS = [1.0, 45.0, 0.5]
GRID = GridSpec((-40.0, -40.0, -1.0, 40.0, 40.0, 5.4), 0.4)


class _Geometry:
    """The duck-typed part of a Batch that the frustum code reads."""

    def __init__(self, batch: int, num_cameras: int) -> None:
        _, k, pose = camera_rig(num_cameras, IMAGE_SIZE)
        self.intrinsics = k.expand(batch, -1, 3, 3).clone()
        self.cam_to_ego = pose.expand(batch, -1, 4, 4).clone()
        self.img_aug = torch.eye(3).expand(batch, num_cameras, 3, 3).clone()
        self.images = torch.zeros(batch, num_cameras, 3, *IMAGE_SIZE)


def _status_kb(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return -1


def peak_cuda_mb(fn: Callable[[], object]) -> float:
    """Peak CUDA memory allocated above the current level while running ``fn`` (MB)."""
    torch.cuda.synchronize()
    base = torch.cuda.memory_allocated()
    torch.cuda.reset_peak_memory_stats()
    result = fn()
    torch.cuda.synchronize()
    peak = torch.cuda.max_memory_allocated()
    del result
    return (peak - base) / 2**20


def peak_rss_mb(fn: Callable[[], object]) -> float:
    """Peak RSS above the current level while running ``fn`` (MB); NaN where Linux's counters are unavailable."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return float("nan")
    base = _status_kb("VmRSS")
    result = fn()
    peak = _status_kb("VmHWM")
    del result
    return (peak - base) / 1024


def time_ms(fn: Callable[[], object], repeat: int) -> tuple[float, float]:
    """(median, best) wall-clock milliseconds over ``repeat`` runs after one warm-up."""
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times), min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--cameras", type=int, default=6)
    parser.add_argument("--channels", type=int, default=64)
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    torch.manual_seed(0)

    b, n, c = args.batch, args.cameras, args.channels
    h, w = IMAGE_SIZE[0] // STRIDE, IMAGE_SIZE[1] // STRIDE
    depths = depth_bin_centers(DEPTH_BINS).to(device)
    d = depths.numel()
    x, y, z = GRID.shape
    v = x * y * z
    geo = _Geometry(b, n)
    for name in ("intrinsics", "cam_to_ego", "img_aug", "images"):
        setattr(geo, name, getattr(geo, name).to(device))

    splatter = FrustumSplatter(GRID, STRIDE)

    def geometry() -> torch.Tensor:
        return splatter.cell_index(geo, h, w, depths)  # (B, N, D, h, w), per-sample cells

    index = geometry()
    plans_t0 = time.perf_counter()
    plans = splatter.plans(geo, h, w, depths)
    sync()
    plan_ms = (time.perf_counter() - plans_t0) * 1e3
    offset = torch.arange(b, device=device).view(b, 1, 1, 1, 1) * v
    flat_index = torch.where(index >= 0, index + offset, index).reshape(-1)

    probs = torch.randn(b, n, d, h, w, device=device).softmax(2).requires_grad_()
    context = torch.randn(b, n, c, h, w, device=device, requires_grad=True)
    grad_volume = torch.randn(b, c, x, y, z, device=device)

    def naive() -> torch.Tensor:
        frustum = probs.view(b, n, d, 1, h, w) * context.view(b, n, 1, c, h, w)
        frustum = frustum.permute(0, 1, 2, 4, 5, 3).reshape(-1, c)
        out = splat(frustum, flat_index, b * v).view(b, x, y, z, c).permute(0, 4, 1, 2, 3).contiguous()
        sync()
        return out

    def fast() -> torch.Tensor:
        out = splat_outer(probs, context, plans).view(b, c, x, y, z)
        sync()
        return out

    point_features = (probs.detach().view(b, n, d, 1, h, w) * context.detach().view(b, n, 1, c, h, w)).requires_grad_()

    def naive_points() -> torch.Tensor:
        rows = point_features.permute(0, 1, 2, 4, 5, 3).reshape(-1, c)
        out = splat(rows, flat_index, b * v).view(b, x, y, z, c).permute(0, 4, 1, 2, 3).contiguous()
        sync()
        return out

    def fast_points() -> torch.Tensor:
        out = splat_points(point_features, plans).view(b, c, x, y, z)
        sync()
        return out

    features = torch.randn(b, n, c, h, w, device=device, requires_grad=True)
    bp = BackwardProjection(c, STRIDE, GRID, out_channels=c, depth_bins=DEPTH_BINS, hidden=0).to(device)

    def backward_projection() -> torch.Tensor:
        out = bp(features, geo).volume  # type: ignore[arg-type]
        sync()
        return out

    def with_backward(fn: Callable[[], torch.Tensor]) -> Callable[[], None]:
        def run() -> None:
            for t in (probs, context, features, point_features):
                t.grad = None
            fn().backward(grad_volume)
            sync()

        return run

    rows = []
    methods = (
        ("naive", naive),
        ("fast", fast),
        ("naive_points", naive_points),
        ("fast_points", fast_points),
        ("backward_projection", backward_projection),
    )
    for name, fn in methods:
        fwd = time_ms(lambda fn=fn: (torch.no_grad()(fn))(), args.repeat)
        both = time_ms(with_backward(fn), args.repeat)
        peak_mb = peak_cuda_mb if device.type == "cuda" else peak_rss_mb
        mem_fwd = peak_mb(lambda fn=fn: torch.no_grad()(fn)())
        mem_both = peak_mb(with_backward(fn))
        rows.append((name, fwd, both, mem_fwd, mem_both))

    # Equality with the reference, values and gradients.
    for t in (probs, context):
        t.grad = None
    ref = naive()
    ref.backward(grad_volume)
    ref_grads = (probs.grad.clone(), context.grad.clone())
    for t in (probs, context):
        t.grad = None
    out = fast()
    out.backward(grad_volume)
    diff = (out - ref).abs().max().item()
    gdiff = [(t.grad - g).abs().max().item() for t, g in zip((probs, context), ref_grads, strict=True)]
    del ref, out
    point_features.grad = None
    ref = naive_points()
    ref.backward(grad_volume)
    ref_grad = point_features.grad.clone()
    point_features.grad = None
    out = fast_points()
    out.backward(grad_volume)
    pdiff = (out - ref).abs().max().item(), (point_features.grad - ref_grad).abs().max().item()
    del ref, out, ref_grad

    geo_ms = time_ms(lambda: geometry(), args.repeat)
    kept = sum(p.num_points_inside for p in plans)
    print(
        f"device={device} threads={torch.get_num_threads()} batch={b} cameras={n} depth_bins={d} "
        f"feature_map={h}x{w} channels={c} grid={x}x{y}x{z} frustum_points={b * n * d * h * w} "
        f"inside_grid={kept} voxel_cell_pairs={sum(p.nnz for p in plans)}"
    )
    what = (
        "peak CUDA memory allocated above the level before the call"
        if device.type == "cuda"
        else "peak RSS above the level before the call (VmHWM after clear_refs)"
    )
    print(f"peak memory = {what}, output volume {b * c * v * 4 / 2**20:.0f} MB included")
    print(
        f"{'method':<22}{'fwd ms (med/best)':>20}{'fwd+bwd ms (med/best)':>24}{'fwd peak MB':>13}{'fwd+bwd peak MB':>17}"
    )
    for name, fwd, both, mem_fwd, mem_both in rows:
        print(
            f"{name:<22}{fwd[0]:>11.1f} /{fwd[1]:>7.1f}{both[0]:>15.1f} /{both[1]:>7.1f}{mem_fwd:>13.0f}{mem_both:>17.0f}"
        )
    print(
        f"geometry (frustum index; the reference LSS recomputes it every forward): {geo_ms[0]:.1f} ms; "
        f"fast-splat plan build (once per geometry, then cached): {plan_ms:.1f} ms"
    )
    print(f"max |fast - naive|: volume {diff:.3g}, d/d depth {gdiff[0]:.3g}, d/d context {gdiff[1]:.3g}")
    print(f"max |fast_points - naive_points|: volume {pdiff[0]:.3g}, d/d features {pdiff[1]:.3g}")
    for label, naive_row, fast_row in (
        ("naive / fast", rows[0], rows[1]),
        ("naive_points / fast_points", rows[2], rows[3]),
    ):
        print(
            f"ratio {label} (median ms): forward {naive_row[1][0] / fast_row[1][0]:.2f}x, "
            f"forward+backward {naive_row[2][0] / fast_row[2][0]:.2f}x"
        )


if __name__ == "__main__":
    main()
