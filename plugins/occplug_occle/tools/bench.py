"""Benchmark OccLE's building blocks (``occplug_occle``), one section per function.

Sections:

* ``scan``: the selective state-space scan of Mamba (:mod:`occplug_occle.blocks.selective_scan`) at one sequence
  length -- :func:`~occplug_occle.blocks.selective_scan.selective_scan_ref` (a Python loop over the ``L`` steps,
  written like ``mamba_ssm``'s reference) against
  :func:`~occplug_occle.blocks.selective_scan.selective_scan_chunked` (chunks of ``--chunk-size`` steps, the
  state carried between chunks) on the same random inputs: ``u``, ``delta = softplus(N(0,1) - 1)``,
  ``A = -exp(N(0, 1))`` ``(D, N)``, ``B``, ``C``, skip ``D`` and gate ``z``. Prints the wall-clock
  milliseconds of each (median and best of ``--repeats`` forward calls after one warm-up, without autograd,
  CUDA synchronised), their ratio ref / chunked, and the largest absolute difference of the outputs. On CUDA in
  float32/16/bfloat16, where ``mamba_ssm``'s kernel loads, that kernel (what ``selective_scan(mode="auto")`` runs
  there) is a third row.

* ``geometry``: the geometric branch (Tab. 4(a)'s module time, the paper: 26.08 ms vs 138.62 ms on an A6000) --
  :class:`~occplug_occle.blocks.geometry_branch.CrossPlaneGeometryBranch` (cross-plane image/LiDAR synergy + 3D header)
  against :class:`~occplug_occle.blocks.geometry_branch.Conv3dDeformableBaseline` (concatenation, Conv3D, 3D deformable
  attention, the same header) side by side on the same random inputs: one frame of a LiDAR and a lifted image
  grid ``(B, 1, C, X, Y, Z)`` at ``--grid X Y Z`` with ``--channels C`` for both modalities and the branch,
  ``--grid-batch B``. Prints, for each, the milliseconds of a forward pass (eval mode, no autograd; median and
  best of ``--repeats`` after one warm-up) and of a forward + backward pass (train mode, ``sum`` of the logits),
  the parameter counts, and the ratio baseline / cross-plane. The CPU recipes' grid is ``--grid 32 32 8``;
  ``--grid 128 128 16`` is a SemanticKITTI-scale grid (the paper's 256 x 256 x 32 at half resolution).

Another section is one more ``bench_<name>(args)`` function and one entry in ``SECTIONS``.

Usage: ``python -m occplug_occle.tools.bench [--section scan|geometry|all] [--length 4096 --dim 64 --state 16 --batch 2]
[--grid 32 32 8 --channels 32 --grid-batch 1] [--repeats 3] [--device cpu|cuda] [--dtype float32|float64]
[--chunk-size 64] [--within steps|segsum]``. Set ``OMP_NUM_THREADS`` for a fixed CPU thread count.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import torch
import torch.nn.functional as F

from ..blocks.geometry_branch import Conv3dDeformableBaseline, CrossPlaneGeometryBranch
from ..blocks.selective_scan import mamba_ssm_kernel, scan_mamba_ssm, selective_scan_chunked, selective_scan_ref


def _time(fn: Callable[[], torch.Tensor], repeats: int, device: torch.device) -> tuple[list[float], torch.Tensor]:
    """Wall-clock seconds of ``repeats`` calls of ``fn`` after one warm-up, and its last output."""
    out = fn()
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        out = fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(time.perf_counter() - start)
    return times, out


def bench_scan(args: argparse.Namespace) -> None:
    """Selective scan: the reference step loop against the chunked scan (and mamba_ssm's kernel) at one length."""
    device, dtype = torch.device(args.device), getattr(torch, args.dtype)
    g = torch.Generator(device="cpu").manual_seed(0)

    def randn(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=g, dtype=dtype).to(device)

    b, length, dim, state = args.batch, args.length, args.dim, args.state
    u, z = randn(b, length, dim), randn(b, length, dim)
    delta = F.softplus(randn(b, length, dim) - 1.0)
    A = -torch.exp(randn(dim, state))
    B, C, D = randn(b, length, state), randn(b, length, state), randn(dim)
    print(
        f"selective scan: B={b} L={length} D={dim} N={state} {args.dtype} on {device}"
        f" ({torch.get_num_threads()} CPU threads), chunk {args.chunk_size} ({args.within})"
    )
    with torch.no_grad():
        t_ref, y_ref = _time(lambda: selective_scan_ref(u, delta, A, B, C, D, z), args.repeats, device)
        t_chunk, y_chunk = _time(
            lambda: selective_scan_chunked(
                u, delta, A, B, C, D, z, chunk_size=args.chunk_size, within_chunk=args.within
            ),
            args.repeats,
            device,
        )
        rows = {"ref": (t_ref, y_ref), "chunked": (t_chunk, y_chunk)}
        kernel = mamba_ssm_kernel() if device.type == "cuda" and dtype != torch.float64 else None
        if kernel is not None:  # what selective_scan's "auto" runs on CUDA where mamba_ssm's kernel loads
            rows["mamba_ssm"] = _time(
                lambda: scan_mamba_ssm(u, delta, A, B, C, D, z, False, kernel), args.repeats, device
            )
    for name, (times, _) in rows.items():
        print(f"  {name:9s} median {statistics.median(times) * 1e3:9.2f} ms   best {min(times) * 1e3:9.2f} ms")
    for name, (times, y) in list(rows.items())[1:]:
        print(f"  ratio ref / {name}: median {statistics.median(t_ref) / statistics.median(times):.2f}x", end="")
        print(f"   best {min(t_ref) / min(times):.2f}x", end="")
        print(
            f"   max |{name} - ref| = {float((y - y_ref).abs().max()):.3e} (max |ref| {float(y_ref.abs().max()):.3e})"
        )


def bench_geometry(args: argparse.Namespace) -> None:
    """Geometric branch: cross-plane synergy against the Conv3D + 3D deformable attention baseline."""
    device, dtype = torch.device(args.device), getattr(torch, args.dtype)
    x, y, z = args.grid
    c, b = args.channels, args.grid_batch
    grid = {"range": [0.0, -y / 2, 0.0, float(x), y / 2, float(z)], "voxel_size": 1.0}
    torch.manual_seed(0)
    models = {
        "cross-plane": CrossPlaneGeometryBranch(c, c, grid, channels=c),
        "conv3d+DA": Conv3dDeformableBaseline(c, c, grid, channels=c),
    }
    g = torch.Generator(device="cpu").manual_seed(0)
    lidar = torch.randn(b, 1, c, x, y, z, generator=g, dtype=dtype).relu().to(device)
    image = torch.randn(b, 1, c, x, y, z, generator=g, dtype=dtype).to(device)
    print(
        f"geometric branch: B={b} grid {x}x{y}x{z} C={c} {args.dtype} on {device}"
        f" ({torch.get_num_threads()} CPU threads)"
    )
    times: dict[str, dict[str, list[float]]] = {}
    for name, model in models.items():
        model = model.to(device=device, dtype=dtype)

        def train_step(model: torch.nn.Module = model) -> torch.Tensor:
            model.zero_grad(set_to_none=True)
            out = model(lidar, image)
            out.sum().backward()
            return out

        model.eval()
        with torch.no_grad():
            forward, _ = _time(lambda model=model: model(lidar, image), args.repeats, device)
        model.train()
        both, _ = _time(train_step, args.repeats, device)
        times[name] = {"forward": forward, "forward+backward": both}
        params = sum(p.numel() for p in model.parameters())
        print(
            f"  {name:12s} forward median {statistics.median(forward) * 1e3:9.2f} ms  best {min(forward) * 1e3:9.2f}"
            f" ms | forward+backward median {statistics.median(both) * 1e3:9.2f} ms  best {min(both) * 1e3:9.2f} ms"
            f" | {params / 1e6:.2f} M parameters"
        )
    for kind in ("forward", "forward+backward"):
        base, ours = times["conv3d+DA"][kind], times["cross-plane"][kind]
        print(
            f"  ratio conv3d+DA / cross-plane, {kind}: median {statistics.median(base) / statistics.median(ours):.2f}x"
            f"   best {min(base) / min(ours):.2f}x"
        )


SECTIONS: dict[str, Callable[[argparse.Namespace], None]] = {"scan": bench_scan, "geometry": bench_geometry}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m occplug_occle.tools.bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--section", choices=[*SECTIONS, "all"], default="all")
    parser.add_argument("--length", type=int, default=4096, help="sequence length L")
    parser.add_argument("--dim", type=int, default=64, help="channels D")
    parser.add_argument("--state", type=int, default=16, help="state size N")
    parser.add_argument("--batch", type=int, default=2)
    parser.add_argument("--grid", type=int, nargs=3, default=[32, 32, 8], metavar=("X", "Y", "Z"), help="geometry")
    parser.add_argument("--channels", type=int, default=32, help="geometry: C of both inputs and of the branch")
    parser.add_argument("--grid-batch", type=int, default=1, help="geometry: batch size")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    parser.add_argument("--chunk-size", type=int, default=64)
    parser.add_argument("--within", choices=["steps", "segsum"], default="steps", help="the chunked scan's inner loop")
    args = parser.parse_args(argv)
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: CUDA is not available")
    for name, section in SECTIONS.items():
        if args.section in (name, "all"):
            section(args)


if __name__ == "__main__":
    main()
