"""Time SparseOcc's own RayIoU ray caster, compiled for the CPU, from a local clone the user provides.

SparseOcc (github.com/MCG-NJU/SparseOcc) casts RayIoU's query rays with a CUDA kernel,
``render_forward_cuda_kernel`` in ``lib/dvr/dvr.cu``. Nothing of that code is part of occplug: this
script reads the kernel's text from the clone at run time, compiles it as plain C++ with a small shim
(CUDA qualifiers dropped, ``blockIdx`` / ``threadIdx`` set by a serial loop over the rays, ``int3``),
and calls it as SparseOcc's ``process_one_sample`` does: once per origin and grid, occupancy 1 / 0 as
float32 in ``(1, 1, Z, Y, X)`` order, origins and ray end points (origin + unit direction) in voxel
units. The compiled extension is cached by ``torch.utils.cpp_extension`` (first build: a minute or two).

Used by ``scripts/bench_metrics.py --sparseocc DIR``; never by the tests.
"""

from __future__ import annotations

import re
import statistics
import time
from pathlib import Path

import torch

from occplug.data import OCC3D_GRID

_SHIM = r"""
#include <torch/extension.h>
#include <algorithm>
#include <cassert>
#include <cfloat>
#include <cmath>
#include <cstdio>
#include <iostream>
#include <string>
#include <vector>
#define __global__
#define __device__
#define __host__
#define __forceinline__ inline
struct int3 { int x, y, z; };
static inline int3 make_int3(int x, int y, int z) { return int3{x, y, z}; }
struct Index3 { unsigned x = 0, y = 0, z = 0; };
static Index3 blockIdx, threadIdx, blockDim;
using std::max;
using std::min;
namespace torch { template <typename T> using RestrictPtrTraits = ::at::DefaultPtrTraits<T>; }  // CUDA-only name
"""

_LAUNCH = r"""
std::vector<torch::Tensor> cast(torch::Tensor sigma, torch::Tensor origin, torch::Tensor points, torch::Tensor tindex) {
    const auto N = points.size(0), M = points.size(1);
    auto gt_dist = -torch::ones({N, M});
    auto pred_dist = -torch::ones({N, M});
    auto coord_index = torch::zeros({N, M, 3});
    blockDim.x = 1;
    threadIdx.x = 0;
    for (int64_t n = 0; n < N; ++n) {
        blockIdx.y = n;
        for (int64_t c = 0; c < M; ++c) {
            blockIdx.x = c;
            render_forward_cuda_kernel<float>(
                sigma.packed_accessor32<float, 5, torch::RestrictPtrTraits>(),
                origin.packed_accessor32<float, 3, torch::RestrictPtrTraits>(),
                points.packed_accessor32<float, 3, torch::RestrictPtrTraits>(),
                tindex.packed_accessor32<float, 2, torch::RestrictPtrTraits>(),
                pred_dist.packed_accessor32<float, 2, torch::RestrictPtrTraits>(),
                gt_dist.packed_accessor32<float, 2, torch::RestrictPtrTraits>(),
                coord_index.packed_accessor32<float, 3, torch::RestrictPtrTraits>(),
                TEST);
        }
    }
    return {pred_dist, gt_dist, coord_index};
}
"""


def _kernel_source(clone: Path) -> str:
    """The defines, enums and ``render_forward_cuda_kernel`` of the clone's ``lib/dvr/dvr.cu``."""
    path = clone / "lib" / "dvr" / "dvr.cu"
    if not path.is_file():
        raise SystemExit(f"error: --sparseocc {clone}: no lib/dvr/dvr.cu (a clone of github.com/MCG-NJU/SparseOcc?)")
    text = path.read_text()
    defines = "\n".join(re.findall(r"^#define\s+MAX_\w+\s+\d+", text, flags=re.M))
    enums = "\n".join(re.findall(r"^enum\s+\w+\s*\{[^}]*\};", text, flags=re.M))
    start = text.index("template <typename scalar_t>\n__global__ void render_forward_cuda_kernel(")
    body = text.index("{", text.index(")", text.index("PhaseName train_phase", start)))
    depth, end = 0, body
    for end in range(body, len(text)):
        depth += {"{": 1, "}": -1}.get(text[end], 0)
        if depth == 0:
            break
    return f"{defines}\n{enums}\n{text[start : end + 1]}\n"


def build(clone: str | Path):
    """The compiled caster (``cast(sigma, origin, points, tindex)``), built from the clone's kernel."""
    from torch.utils.cpp_extension import load_inline

    source = _SHIM + _kernel_source(Path(clone)) + _LAUNCH
    return load_inline("sparseocc_dvr_cpu", [source], functions=["cast"], extra_cflags=["-O3"], verbose=False)


def official_cast(module, labels: torch.Tensor, origins: torch.Tensor, directions: torch.Tensor, free: int = 17):
    """SparseOcc's ``process_one_sample`` casting: ``(distance (T * D,) m, hit voxel (T * D, 3))``."""
    occ = (labels != free).float().permute(2, 1, 0)[None, None].contiguous()
    offset = torch.tensor(OCC3D_GRID.lower, dtype=torch.float32)
    size = float(OCC3D_GRID.voxel_size[0])
    rays = directions.float()
    tindex = torch.zeros(1, rays.shape[0])
    dists, voxels = [], []
    for origin in origins.float():
        o = ((origin - offset) / size)[None, None]
        p = ((rays + origin - offset) / size)[None]
        dist, _, coord = module.cast(occ, o.contiguous(), p.contiguous(), tindex)
        dists.append(dist[0] * size)
        voxels.append(coord[0].long())
    return torch.cat(dists), torch.cat(voxels)


def official_cast_seconds(clone: str | Path, pred, labels, origins, repeats: int = 3) -> float:
    """Median seconds of casting every query ray from ``origins`` through ``pred`` and ``labels`` (both
    grids, as SparseOcc's RayIoU does per sample) with the compiled official caster."""
    from occplug.metrics import query_ray_directions

    start = time.perf_counter()
    module = build(clone)
    print(f"SparseOcc caster built (or loaded from torch's extension cache) in {time.perf_counter() - start:.1f} s")
    directions = query_ray_directions()
    official_cast(module, labels, origins[:1], directions[:10])  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for grid in (pred, labels):
            official_cast(module, grid, origins, directions)
        times.append(time.perf_counter() - start)
    return statistics.median(times)
