#!/usr/bin/env python
"""Benchmark OccLE's building blocks (``occplug_occle``), one section per function.

Sections:

* ``scan``: the selective state-space scan of Mamba (:mod:`occplug_occle.selective_scan`) at one sequence
  length -- :func:`~occplug_occle.selective_scan.selective_scan_ref` (a Python loop over the ``L`` steps,
  written like ``mamba_ssm``'s reference) against
  :func:`~occplug_occle.selective_scan.selective_scan_chunked` (chunks of ``--chunk-size`` steps, the
  state carried between chunks) on the same random inputs: ``u``, ``delta = softplus(N(0,1) - 1)``,
  ``A = -exp(N(0, 1))`` ``(D, N)``, ``B``, ``C``, skip ``D`` and gate ``z``. Prints the wall-clock
  milliseconds of each (median and best of ``--repeats`` forward calls after one warm-up, without autograd,
  CUDA synchronised), their ratio ref / chunked, and the largest absolute difference of the outputs.

Another section (e.g. the geometric branch against a Conv3D baseline) is one more ``bench_<name>(args)``
function and one entry in ``SECTIONS``.

Usage: ``python scripts/bench_occle.py [--section scan] [--length 4096 --dim 64 --state 16 --batch 2]
[--repeats 3] [--device cpu|cuda] [--dtype float32|float64] [--chunk-size 64] [--within steps|segsum]``.
Set ``OMP_NUM_THREADS`` for a fixed CPU thread count.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import torch
import torch.nn.functional as F

from occplug_occle.selective_scan import selective_scan_chunked, selective_scan_ref


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
    """Selective scan: the reference step loop against the chunked scan at one sequence length."""
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
    for name, times in (("ref", t_ref), ("chunked", t_chunk)):
        print(f"  {name:8s} median {statistics.median(times) * 1e3:9.2f} ms   best {min(times) * 1e3:9.2f} ms")
    print(f"  ratio ref / chunked: median {statistics.median(t_ref) / statistics.median(t_chunk):.2f}x", end="")
    print(f"   best {min(t_ref) / min(t_chunk):.2f}x")
    print(
        f"  max |chunked - ref| = {float((y_chunk - y_ref).abs().max()):.3e} (max |ref| {float(y_ref.abs().max()):.3e})"
    )


SECTIONS: dict[str, Callable[[argparse.Namespace], None]] = {"scan": bench_scan}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--section", choices=[*SECTIONS, "all"], default="all")
    parser.add_argument("--length", type=int, default=4096, help="sequence length L")
    parser.add_argument("--dim", type=int, default=64, help="channels D")
    parser.add_argument("--state", type=int, default=16, help="state size N")
    parser.add_argument("--batch", type=int, default=2)
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
