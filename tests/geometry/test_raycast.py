"""Exact voxel traversal: the vectorised walk equals a slow per-ray reference, plus hand cases."""

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from occplug.geometry import GridSpec, first_hit, observed_mask, traversed_mask
from occplug.geometry.raycast import clearance, first_hits

ROOT = Path(__file__).resolve().parents[2]

# ----------------------------------------------------------------------------------------------
# The reference: per ray, in Python floats. Independent of the DDA: it collects every t at which
# the ray crosses a voxel plane, sorts them, and names the voxel of each interval by the floor of
# its midpoint, so a voxel touched for zero length (an edge or corner) never appears.


def reference_walk(grid, origin, direction, t_max):
    """[(voxel (i, j, k), entry distance)] in traversal order along ``[0, t_max)``."""
    g = [(origin[a] - grid.lower[a]) / grid.voxel_size[a] for a in range(3)]
    dg = [direction[a] / grid.voxel_size[a] for a in range(3)]
    n = grid.shape
    t_lo, t_hi = 0.0, t_max
    for a in range(3):
        if dg[a] == 0:
            if not 0 <= g[a] < n[a]:
                return []
        else:
            ta, tb = (0 - g[a]) / dg[a], (n[a] - g[a]) / dg[a]
            t_lo, t_hi = max(t_lo, min(ta, tb)), min(t_hi, max(ta, tb))
    if not t_lo < t_hi:
        return []
    ts = {t_lo, t_hi}
    for a in range(3):
        if dg[a] != 0:
            for k in range(n[a] + 1):
                t = (k - g[a]) / dg[a]
                if t_lo < t < t_hi:
                    ts.add(t)
    ts = sorted(ts)
    out = []
    for a, b in zip(ts, ts[1:], strict=False):
        mid = 0.5 * (a + b)
        voxel = tuple(math.floor(g[ax] + mid * dg[ax]) for ax in range(3))
        if not out or out[-1][0] != voxel:
            out.append((voxel, a))
    return out


def reference_first_hit(occ, grid, origin, direction, t_max):
    for voxel, t in reference_walk(grid, origin, direction, t_max):
        if occ[voxel]:
            return voxel, t
    return (-1, -1, -1), math.inf


def reference_traversed(grid, origin, endpoint):
    delta = [endpoint[a] - origin[a] for a in range(3)]
    length = math.sqrt(sum(d * d for d in delta))
    voxels = set()
    if length > 0:
        direction = [d / length for d in delta]
        voxels = {v for v, _ in reference_walk(grid, origin, direction, length)}
    end = tuple(math.floor((endpoint[a] - grid.lower[a]) / grid.voxel_size[a]) for a in range(3))
    if all(0 <= end[a] < grid.shape[a] for a in range(3)):
        voxels.add(end)
    return voxels


def reference_observed(occ, grid, origin, direction, t_max):
    voxels = set()
    for voxel, _ in reference_walk(grid, origin, direction, t_max):
        voxels.add(voxel)
        if occ[voxel]:
            break
    return voxels


def to_mask(voxels, shape):
    mask = torch.zeros(shape, dtype=torch.bool)
    for v in voxels:
        mask[v] = True
    return mask


# ----------------------------------------------------------------------------------------------


def random_case(seed, rays=400):
    """A random anisotropic grid, occupancy and rays (many starting outside, many axis-parallel)."""
    gen = torch.Generator().manual_seed(seed)
    shape = torch.randint(3, 9, (3,), generator=gen).tolist()
    size = (0.3 + torch.rand(3, generator=gen, dtype=torch.float64)).tolist()
    lower = (torch.rand(3, generator=gen, dtype=torch.float64) * 4 - 2).tolist()
    grid = GridSpec(range=[*lower, *(lower[a] + shape[a] * size[a] for a in range(3))], voxel_size=size)
    occ = torch.rand(grid.shape, generator=gen) < 0.2
    extent = torch.tensor([shape[a] * size[a] for a in range(3)], dtype=torch.float64)
    spread = torch.rand(rays, 3, generator=gen, dtype=torch.float64) * 2 - 0.5  # half the origins outside
    origins = torch.tensor(lower, dtype=torch.float64) + spread * extent
    directions = torch.randn(rays, 3, generator=gen, dtype=torch.float64)
    kind = torch.randint(0, 5, (rays,), generator=gen)
    targets = (
        torch.tensor(lower, dtype=torch.float64) + torch.rand(rays, 3, generator=gen, dtype=torch.float64) * extent
    )
    aimed = kind == 4  # aimed at a point inside the grid
    directions[aimed] = targets[aimed] - origins[aimed]
    axis = torch.randint(0, 3, (rays,), generator=gen)
    rows = torch.arange(rays)
    planar = kind == 1  # one zero component
    directions[rows[planar], axis[planar]] = 0.0
    parallel = kind == 2  # exactly along an axis, either sign
    directions[parallel] = 0.0
    sign = torch.where(torch.rand(int(parallel.sum()), generator=gen) < 0.5, -1.0, 1.0).double()
    directions[rows[parallel], axis[parallel]] = sign
    directions = directions / directions.norm(dim=-1, keepdim=True)
    t_max = torch.rand(rays, generator=gen, dtype=torch.float64) * 2 * float(extent.norm())
    t_max[kind == 3] = math.inf
    return grid, occ, origins, directions, t_max


@pytest.mark.parametrize("seed", range(4))
def test_first_hit_matches_reference_on_random_rays(seed):
    grid, occ, origins, directions, t_max = random_case(seed)
    index, distance = first_hit(occ, grid, origins, directions, t_max)
    assert index.dtype == torch.int64 and distance.dtype == torch.float64
    hits = 0
    for r in range(origins.shape[0]):
        ref_voxel, ref_t = reference_first_hit(occ, grid, origins[r].tolist(), directions[r].tolist(), float(t_max[r]))
        assert tuple(index[r].tolist()) == ref_voxel, f"ray {r}"
        if ref_t == math.inf:
            assert distance[r] == math.inf
        else:
            hits += 1
            assert abs(float(distance[r]) - ref_t) < 1e-9
    assert hits > origins.shape[0] // 10  # the case is not vacuous


@pytest.mark.parametrize("seed", range(4, 8))
def test_traversed_and_observed_masks_match_reference(seed):
    grid, occ, origins, directions, t_max = random_case(seed)
    # segments: finite lengths only; some endpoints far outside the grid
    length = torch.where(torch.isinf(t_max), torch.full_like(t_max, 3.0), t_max)
    endpoints = origins + directions * length[:, None]
    expected = set()
    observed = set()
    for r in range(origins.shape[0]):
        expected |= reference_traversed(grid, origins[r].tolist(), endpoints[r].tolist())
        observed |= reference_observed(occ, grid, origins[r].tolist(), directions[r].tolist(), float(t_max[r]))
    assert torch.equal(traversed_mask(grid, origins, endpoints), to_mask(expected, grid.shape))
    assert torch.equal(observed_mask(occ, grid, origins, directions, t_max), to_mask(observed, grid.shape))
    # per ray, too (a union could hide a missing voxel that another ray covers)
    for r in range(0, origins.shape[0], 7):
        one = traversed_mask(grid, origins[r : r + 1], endpoints[r : r + 1])
        assert torch.equal(
            one, to_mask(reference_traversed(grid, origins[r].tolist(), endpoints[r].tolist()), grid.shape)
        )


def test_float32_inputs_give_float32_distances_and_same_voxels():
    grid, occ, origins, directions, t_max = random_case(11)
    i64, d64 = first_hit(occ, grid, origins, directions, t_max)
    i32, d32 = first_hit(occ, grid, origins.float(), directions.float(), t_max.float())
    assert d32.dtype == torch.float32
    assert (i32 == i64).all(-1).float().mean() > 0.99  # float32 inputs are rounded, rarely a boundary moves
    same = (i32 == i64).all(-1) & torch.isfinite(d64)
    assert torch.allclose(d32[same].double(), d64[same], atol=1e-4)


# ----------------------------------------------------------------------------------------------
# Hand cases on a unit grid [0, 4)^3.

UNIT = GridSpec(range=(0, 0, 0, 4, 4, 4), voxel_size=1.0)


def rays(*pairs):
    o = torch.tensor([p[0] for p in pairs], dtype=torch.float64)
    d = torch.tensor([p[1] for p in pairs], dtype=torch.float64)
    return o, d / d.norm(dim=-1, keepdim=True)


def test_hit_from_outside_along_an_axis():
    occ = torch.zeros(UNIT.shape, dtype=torch.bool)
    occ[2, 0, 0] = True
    o, d = rays(((-1.0, 0.5, 0.5), (1, 0, 0)), ((5.0, 0.5, 0.5), (-1, 0, 0)), ((-1.0, 1.5, 0.5), (1, 0, 0)))
    index, distance = first_hit(occ, UNIT, o, d, 100.0)
    assert index.tolist() == [[2, 0, 0], [2, 0, 0], [-1, -1, -1]]
    assert distance[:2].tolist() == [3.0, 2.0] and distance[2] == math.inf


def test_origin_inside_an_occupied_voxel_hits_at_zero():
    occ = torch.zeros(UNIT.shape, dtype=torch.bool)
    occ[1, 1, 1] = True
    index, distance = first_hit(occ, UNIT, *rays(((1.5, 1.2, 1.7), (0.3, -1, 2))), 10.0)
    assert index.tolist() == [[1, 1, 1]] and distance.tolist() == [0.0]


def test_max_distance_is_half_open():
    occ = torch.zeros(UNIT.shape, dtype=torch.bool)
    occ[3, 0, 0] = True
    o, d = rays(((0.5, 0.5, 0.5), (1, 0, 0)))
    assert first_hit(occ, UNIT, o, d, 2.5)[0].tolist() == [[-1, -1, -1]]  # entered at exactly 2.5
    assert first_hit(occ, UNIT, o, d, 2.5001)[0].tolist() == [[3, 0, 0]]


def test_diagonal_through_corners_steps_diagonally():
    o, d = rays(((0.5, 0.5, 0.5), (1, 1, 0)))
    mask = traversed_mask(UNIT, o, o + d * 10)
    assert sorted(map(tuple, mask.nonzero().tolist())) == [(0, 0, 0), (1, 1, 0), (2, 2, 0), (3, 3, 0)]
    o, d = rays(((0.0, 0.0, 0.0), (1, 1, 1)))  # the main diagonal, from the grid corner
    mask = traversed_mask(UNIT, o, o + d * 10)
    assert sorted(map(tuple, mask.nonzero().tolist())) == [(i, i, i) for i in range(4)]


def test_boundary_starts_and_endpoints():
    # starting on a boundary and moving down: the voxel behind is not traversed
    o, d = rays(((2.0, 0.5, 0.5), (-1, 0, 0)))
    assert sorted(map(tuple, traversed_mask(UNIT, o, o + d * 1.5).nonzero().tolist())) == [(0, 0, 0), (1, 0, 0)]
    # an endpoint exactly on a boundary: its voxel (floor convention) is included
    o = torch.tensor([[0.5, 0.5, 0.5]], dtype=torch.float64)
    e = torch.tensor([[2.0, 0.5, 0.5]], dtype=torch.float64)
    assert sorted(map(tuple, traversed_mask(UNIT, o, e).nonzero().tolist())) == [(0, 0, 0), (1, 0, 0), (2, 0, 0)]
    # a zero-length segment marks only its own voxel; a segment entirely outside marks nothing
    assert traversed_mask(UNIT, o, o).nonzero().tolist() == [[0, 0, 0]]
    far = torch.tensor([[10.0, 10.0, 10.0]], dtype=torch.float64)
    assert not traversed_mask(UNIT, far, far + 1).any()


def test_ray_in_a_face_plane_and_grazing_rays():
    # a ray lying in the plane y = 1 traverses the voxels with j = 1 (floor convention)
    o, d = rays(((-1.0, 1.0, 0.5), (1, 0, 0)))
    assert sorted(map(tuple, traversed_mask(UNIT, o, o + d * 10).nonzero().tolist())) == [(i, 1, 0) for i in range(4)]
    # touching the grid only along an outer edge is no traversal
    o, d = rays(((-1.0, 4.0, 0.5), (1, 0, 0)), ((-1.0, -1.0, 0.5), (1, 1, 0)))
    occ = torch.ones(UNIT.shape, dtype=torch.bool)
    index, distance = first_hit(occ, UNIT, o, d, 100.0)
    assert index[0].tolist() == [-1, -1, -1]
    assert index[1].tolist() == [0, 0, 0] and abs(float(distance[1]) - math.sqrt(2)) < 1e-12


def test_observed_mask_stops_at_first_occupied_voxel():
    occ = torch.zeros(UNIT.shape, dtype=torch.bool)
    occ[2, 0, 0] = True
    mask = observed_mask(occ, UNIT, *rays(((-3.0, 0.5, 0.5), (1, 0, 0))), 100.0)
    assert sorted(map(tuple, mask.nonzero().tolist())) == [(0, 0, 0), (1, 0, 0), (2, 0, 0)]


# ----------------------------------------------------------------------------------------------
# first_hits: several grids at once, exit distances, and exact empty-space skipping.


def reference_exit(grid, origin, direction, voxel):
    """Where the ray leaves ``voxel``: the nearest far boundary over the moving axes."""
    out = math.inf
    for a in range(3):
        if direction[a] != 0:
            g = (origin[a] - grid.lower[a]) / grid.voxel_size[a]
            dg = direction[a] / grid.voxel_size[a]
            out = min(out, (voxel[a] + (dg > 0) - g) / dg)
    return out


def sparse_case(seed, rays=1200):
    """A larger random grid with long free runs (so skipping jumps far), plus a denser second grid."""
    gen = torch.Generator().manual_seed(100 + seed)
    shape = torch.randint(12, 40, (3,), generator=gen).tolist()
    size = (0.3 + torch.rand(3, generator=gen, dtype=torch.float64)).tolist()
    lower = (torch.rand(3, generator=gen, dtype=torch.float64) * 4 - 2).tolist()
    grid = GridSpec(range=[*lower, *(lower[a] + shape[a] * size[a] for a in range(3))], voxel_size=size)
    occ = torch.stack([torch.rand(grid.shape, generator=gen) < p for p in (0.01, 0.08)])
    extent = torch.tensor([shape[a] * size[a] for a in range(3)], dtype=torch.float64)
    origins = (
        torch.tensor(lower, dtype=torch.float64)
        + (torch.rand(rays, 3, generator=gen, dtype=torch.float64) * 1.6 - 0.3) * extent
    )
    directions = torch.randn(rays, 3, generator=gen, dtype=torch.float64)
    rows = torch.arange(rays)
    axis = torch.randint(0, 3, (rays,), generator=gen)
    directions[rows[rows % 5 == 1], axis[rows % 5 == 1]] = 0.0  # in a plane
    parallel = rows[rows % 5 == 2]
    directions[parallel] = 0.0
    directions[parallel, axis[parallel]] = 1.0 - 2.0 * (parallel % 2).double()  # along an axis, either sign
    directions = directions / directions.norm(dim=-1, keepdim=True)
    t_max = torch.where(rows % 3 == 0, torch.inf, torch.rand(rays, generator=gen, dtype=torch.float64) * extent.norm())
    return grid, occ, origins, directions, t_max


@pytest.mark.parametrize("seed", range(3))
def test_first_hits_match_reference_in_several_grids(seed):
    grid, occ, origins, directions, t_max = sparse_case(seed)
    hits = first_hits(occ, grid, origins, directions, t_max, kernel="torch")
    assert hits.index.shape == (2, origins.shape[0], 3) and hits.exit.dtype == torch.float64
    found = 0
    for g in range(2):
        for r in range(origins.shape[0]):
            o, d = origins[r].tolist(), directions[r].tolist()
            voxel, t = reference_first_hit(occ[g], grid, o, d, float(t_max[r]))
            assert tuple(hits.index[g, r].tolist()) == voxel, f"grid {g} ray {r}"
            if voxel[0] < 0:
                assert hits.entry[g, r] == math.inf and hits.exit[g, r] == math.inf
                continue
            found += 1
            assert abs(float(hits.entry[g, r]) - t) < 1e-9
            assert abs(float(hits.exit[g, r]) - reference_exit(grid, o, d, voxel)) < 1e-9
    assert found > origins.shape[0] // 8  # not vacuous
    plain = first_hits(occ, grid, origins, directions, t_max, skip=False, kernel="torch")
    assert all(torch.equal(a, b) for a, b in zip(hits, plain, strict=True))  # skipping changes nothing
    assert torch.equal(hits.index[1], first_hit(occ[1], grid, origins, directions, t_max)[0])


def test_skipping_lands_exactly_on_ties():
    # unit voxels, origins on voxel centres and lattice points, directions through voxel edges and
    # corners: ties everywhere, and the jumps must reproduce the single steps' diagonal moves
    grid = GridSpec((0, 0, 0, 48, 48, 12), 1.0)
    occ = torch.rand(grid.shape, generator=torch.Generator().manual_seed(0)) < 0.01
    occ[[0, -1]] = True  # walls at both x ends: most rays end on one after long jumps
    steps = [(a, b, c) for a in (-2, -1, 0, 1, 2) for b in (-1, 0, 1, 3) for c in (-1, 0, 1) if (a, b, c) != (0, 0, 0)]
    starts = [(24.5, 24.5, 6.5), (24.0, 24.0, 6.0), (3.5, 40.0, 2.5), (47.5, 0.5, 11.5)]
    origins = torch.tensor([s for s in starts for _ in steps], dtype=torch.float64)
    directions = torch.tensor(steps * len(starts), dtype=torch.float64)
    directions = directions / directions.norm(dim=-1, keepdim=True)
    skipped = first_hits(occ[None], grid, origins, directions, math.inf, kernel="torch")
    plain = first_hits(occ[None], grid, origins, directions, math.inf, skip=False, kernel="torch")
    assert all(torch.equal(a, b) for a, b in zip(skipped, plain, strict=True))
    single = first_hit(occ, grid, origins, directions, math.inf)
    assert torch.equal(skipped.index[0], single[0]) and torch.equal(skipped.entry[0], single[1])
    assert (skipped.index[0, :, 0] >= 0).sum() > 2 * len(steps)


def tie_case():
    """Unit voxels, origins on voxel centres, faces and lattice points, directions through voxel edges and
    corners and along faces: ties everywhere (the case of :func:`test_skipping_lands_exactly_on_ties`)."""
    grid = GridSpec((0, 0, 0, 48, 48, 12), 1.0)
    occ = torch.rand(grid.shape, generator=torch.Generator().manual_seed(0)) < 0.01
    occ[[0, -1]] = True
    steps = [(a, b, c) for a in (-2, -1, 0, 1, 2) for b in (-1, 0, 1, 3) for c in (-1, 0, 1) if (a, b, c) != (0, 0, 0)]
    starts = [(24.5, 24.5, 6.5), (24.0, 24.0, 6.0), (3.5, 40.0, 2.5), (47.5, 0.5, 11.5), (10.0, 24.0, 6.0)]
    origins = torch.tensor([s for s in starts for _ in steps], dtype=torch.float64)
    directions = torch.tensor(steps * len(starts), dtype=torch.float64)
    return grid, occ[None], origins, directions / directions.norm(dim=-1, keepdim=True), math.inf


@pytest.mark.parametrize("case", ["sparse-0", "sparse-1", "sparse-2", "random-0", "random-5", "ties"])
def test_compiled_walk_equals_the_torch_walk_bit_for_bit(case):
    pytest.importorskip("numba")
    if case == "ties":
        grid, occ, origins, directions, t_max = tie_case()
    elif case.startswith("sparse"):
        grid, occ, origins, directions, t_max = sparse_case(int(case[-1]))
    else:
        grid, one, origins, directions, t_max = random_case(int(case[-1]), rays=3000)
        occ = torch.stack([one, one.flip(0), torch.zeros_like(one)])  # the empty grid: every ray runs to its end
    fast = first_hits(occ, grid, origins, directions, t_max, kernel="numba")
    for skip in (True, False):
        reference = first_hits(occ, grid, origins, directions, t_max, skip=skip, kernel="torch")
        for name, a, b in zip(fast._fields, fast, reference, strict=True):
            assert torch.equal(a, b), f"{name} differs (skip={skip})"
    assert (fast.index[..., 0] >= 0).sum() > origins.shape[0] // 20  # not vacuous
    auto = first_hits(occ, grid, origins.float(), directions.float(), t_max)  # auto picks the compiled walk
    assert all(
        torch.equal(a, b)
        for a, b in zip(
            auto, first_hits(occ, grid, origins.float(), directions.float(), t_max, kernel="torch"), strict=True
        )
    )


def test_kernel_choice_is_checked(monkeypatch):
    from occplug.geometry import raycast_numba

    grid, occ, origins, directions, t_max = sparse_case(0)
    with pytest.raises(ValueError, match="kernel must be 'auto', 'torch' or 'numba'"):
        first_hits(occ, grid, origins, directions, t_max, kernel="cuda")
    monkeypatch.setattr(raycast_numba, "available", lambda: False)
    with pytest.raises(ValueError, match="numba is not installed"):
        first_hits(occ, grid, origins, directions, t_max, kernel="numba")
    fallback = first_hits(occ, grid, origins, directions, t_max)  # auto without numba: the torch walk
    assert all(
        torch.equal(a, b)
        for a, b in zip(fallback, first_hits(occ, grid, origins, directions, t_max, kernel="torch"), strict=True)
    )


def test_clearance_is_the_capped_chebyshev_distance():
    occ = torch.zeros(9, 8, 5, dtype=torch.bool)
    occ[2, 3, 1] = occ[7, 7, 4] = True
    idx = torch.stack(torch.meshgrid(*(torch.arange(n) for n in occ.shape), indexing="ij"), -1)
    points = occ.nonzero()
    brute = (idx[:, :, :, None, :] - points).abs().amax(-1).amin(-1)
    assert torch.equal(clearance(occ, cap=16), brute)
    assert torch.equal(clearance(occ, cap=3), brute.clamp(max=3))
    assert (clearance(torch.zeros(3, 3, 3, dtype=torch.bool), cap=5) == 5).all()


def test_empty_inputs():
    o = torch.zeros(0, 3)
    index, distance = first_hit(torch.zeros(UNIT.shape, dtype=torch.bool), UNIT, o, o, 1.0)
    assert index.shape == (0, 3) and distance.shape == (0,)
    assert not traversed_mask(UNIT, o, o).any()


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_gpu_equals_cpu():
    grid, occ, origins, directions, t_max = random_case(3, rays=2000)
    cpu = first_hit(occ, grid, origins, directions, t_max)
    gpu = first_hit(occ.cuda(), grid, origins.cuda(), directions.cuda(), t_max.cuda())
    assert torch.equal(cpu[0], gpu[0].cpu()) and torch.equal(cpu[1], gpu[1].cpu())
    endpoints = origins + directions * 3
    on_gpu = traversed_mask(grid, origins.cuda(), endpoints.cuda()).cpu()
    assert torch.equal(traversed_mask(grid, origins, endpoints), on_gpu)


def test_torch_fuses_addcmul_answers_for_the_cpu_kernels_in_use():
    """On an x86 CPU with FMA torch's vectorised kernels fuse; under the scalar kernels (``default``) they do not."""
    pytest.importorskip("numba")
    from occplug.geometry.raycast_numba import torch_fuses_addcmul

    if torch.backends.cpu.get_cpu_capability() not in ("AVX2", "AVX512"):
        pytest.skip("not an x86 CPU with AVX2 / AVX-512")
    assert torch_fuses_addcmul()
    code = "from occplug.geometry.raycast_numba import torch_fuses_addcmul; print(torch_fuses_addcmul())"
    env = {**os.environ, "ATEN_CPU_CAPABILITY": "default"}
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True)
    assert done.stdout.strip() == "False", done.stderr[-2000:]


def test_the_compiled_walk_follows_torch_s_rounding_where_torch_does_not_fuse():
    """Under ``ATEN_CPU_CAPABILITY=default`` torch's ``addcmul`` rounds twice: the compiled walk asks torch and
    rounds as it does, so it still equals the torch walk bit for bit and no ray reads past the grid (it did: the
    set-up's exit distance, rounded twice, let a fused step cross the last boundary, an index past the grid). On
    x86 the scalar kernels round twice; :func:`torch_fuses_addcmul` answers whatever a platform does."""
    pytest.importorskip("numba")
    code = """
import torch
from occplug.geometry.raycast import first_hits
from tests.geometry.test_raycast import random_case, sparse_case, tie_case
for grid, occ, origins, directions, t_max in (tie_case(), sparse_case(1), random_case(5, rays=3000)):
    occ = occ if occ.dim() == 4 else occ[None]
    fast = first_hits(occ, grid, origins, directions, t_max, kernel="numba")
    reference = first_hits(occ, grid, origins, directions, t_max, kernel="torch")
    assert all(torch.equal(a, b) for a, b in zip(fast, reference, strict=True))
    assert bool((fast.index < torch.tensor(grid.shape)).all())
print("ok")
"""
    env = {**os.environ, "ATEN_CPU_CAPABILITY": "default", "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr[-2000:]
