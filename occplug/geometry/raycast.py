"""Exact ray traversal of voxel grids (Amanatides & Woo, 1987), vectorised over rays.

All rays advance together, one voxel per loop step, so the Python loop runs over *steps* (at most
``X + Y + Z``), never over rays; finished rays are dropped from the working set as they end.
Everything runs on the device of the inputs (CPU or GPU), in float64 so voxel boundaries are
resolved exactly enough that results match a per-ray reference.

Semantics shared by every function here
---------------------------------------
* A ray is ``origin + t * direction`` with ``direction`` a unit vector, so ``t`` is in metres; only
  ``t >= 0`` counts. Origins may lie inside or outside the grid.
* A ray **traverses** a voxel when it passes through the voxel's *interior* for a positive length.
  Touching a voxel only at a face, edge or corner (a set of length zero) is not a traversal; in
  particular a ray that passes exactly through a voxel edge or corner steps diagonally, changing all
  tied axes at once (the deterministic tie rule), and a ray lying exactly in a voxel face plane
  traverses the voxels on the side its floor index selects.
* A voxel's **entry distance** is the ``t`` at which the ray enters it, ``max(0, ...)``: a ray
  starting inside a voxel enters it at ``t = 0``.
* Voxel ``(i, j, k)`` spans ``[x_min + i * dx, x_min + (i + 1) * dx)`` etc.
  (:class:`~occplug.geometry.GridSpec`).
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple

import torch
from torch import Tensor

from .grid import GridSpec

__all__ = ["RayHits", "clearance", "first_hit", "first_hits", "observed_mask", "traversed_mask"]


def _grid_tensors(grid: GridSpec, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    lower = torch.tensor(grid.lower, dtype=torch.float64, device=device)
    size = torch.tensor(grid.voxel_size, dtype=torch.float64, device=device)
    shape = torch.tensor(grid.shape, dtype=torch.int64, device=device)
    return lower, size, shape


def _clip_to_grid(g: Tensor, dg: Tensor, shape: Tensor) -> tuple[Tensor, Tensor]:
    """Slab test in grid units: the ``t`` interval ``(t_in, t_out)`` of each ray inside the grid box.

    ``g`` are origins in voxel units (voxel ``i`` spans ``[i, i + 1)``), ``dg`` directions in voxel
    units per metre. Axis-parallel components keep the ray inside (``(-inf, inf)``) or outside
    (empty) that slab for every ``t``.
    """
    n = shape.to(g.dtype)
    moving = dg != 0
    safe = torch.where(moving, dg, torch.ones_like(dg))
    t_a = (0.0 - g) / safe
    t_b = (n - g) / safe
    t_lo = torch.where(moving, torch.minimum(t_a, t_b), torch.full_like(g, -torch.inf))
    t_hi = torch.where(moving, torch.maximum(t_a, t_b), torch.full_like(g, torch.inf))
    inside_slab = (g >= 0) & (g < n)
    t_lo = torch.where(moving | inside_slab, t_lo, torch.full_like(g, torch.inf))
    t_hi = torch.where(moving | inside_slab, t_hi, torch.full_like(g, -torch.inf))
    t_in = t_lo.amax(dim=-1).clamp_min(0.0)
    t_out = t_hi.amin(dim=-1)
    return t_in, t_out


def _start_voxel(g: Tensor, dg: Tensor, t_in: Tensor, shape: Tensor) -> Tensor:
    """The voxel a ray occupies just after ``t_in``: floor of the entry point, except that an axis
    moving in the negative direction takes ``ceil - 1`` (so a ray leaving a boundary at ``t_in``
    starts in the voxel it moves into, not the one it merely touches)."""
    p = g + t_in[:, None] * dg
    idx = torch.where(dg < 0, torch.ceil(p) - 1, torch.floor(p)).to(torch.int64)
    return torch.minimum(torch.maximum(idx, torch.zeros_like(idx)), shape - 1)


class _Walk:
    """The traversal state of a set of rays: one voxel per ray, advanced by :meth:`advance`.

    Rays that finish stay in the arrays (marked dead, their voxel redirected to a trash slot one
    past the last voxel) until enough of them have finished to make compacting worthwhile.

    Attributes (one row per ray still in the working set):
        ray: ``(A,)`` int64 index of each ray in the caller's ray order.
        alive: ``(A,)`` bool, whether the ray is still traversing.
        index: ``(A, 3)`` float64 current voxel (integers held exactly in float64).
        t_entry: ``(A,)`` float64 distance at which the current voxel was entered.
    """

    _ROW_FIELDS = ("ray", "alive", "index", "flat", "t_entry", "t_stop", "offset", "inv", "step")

    def __init__(self, grid: GridSpec, origins: Tensor, directions: Tensor, max_distance: Tensor) -> None:
        device = origins.device
        lower, size, shape = _grid_tensors(grid, device)
        self.trash = int(shape.prod())
        g = (origins.to(torch.float64) - lower) / size
        dg = directions.to(torch.float64) / size
        t_in, _ = _clip_to_grid(g, dg, shape)
        moving = dg != 0
        step = torch.sign(dg) * moving
        inv = torch.where(moving, 1.0 / torch.where(moving, dg, torch.ones_like(dg)), 0.0)
        # The boundary ahead on an axis lies at index + 1 (moving up) or index (moving down):
        # t = index * inv + offset, evaluated by the same expression at every step and for the exit.
        offset = torch.where(moving, ((step > 0).to(torch.float64) - g) * inv, torch.inf)
        last = torch.where(step > 0, (shape - 1).to(torch.float64), torch.zeros_like(g))
        t_exit = torch.where(moving, torch.addcmul(offset, last, inv), torch.inf).amin(-1)
        t_stop = torch.minimum(t_exit, max_distance)
        rows = torch.nonzero(t_in < t_stop).squeeze(1)
        self.ray = rows
        self.t_entry, self.t_stop = t_in[rows], t_stop[rows]
        self.offset, self.inv, self.step = offset[rows], inv[rows], step[rows]
        self.index = _start_voxel(g[rows], dg[rows], self.t_entry, shape).to(torch.float64)
        self.strides = torch.tensor(
            [grid.shape[1] * grid.shape[2], grid.shape[2], 1], dtype=torch.float64, device=device
        )
        self.flat = (self.index * self.strides).sum(-1)
        self.alive = torch.ones_like(self.ray, dtype=torch.bool)
        self.count = int(rows.numel())

    def __len__(self) -> int:
        return self.count

    def voxels(self) -> Tensor:
        """``(A,)`` int64 row-major index of each row's voxel into a flattened ``(X, Y, Z)`` grid,
        or the trash index ``X * Y * Z`` for dead rows."""
        return torch.where(self.alive, self.flat, self.trash).to(torch.int64)

    def kill(self, rows: Tensor) -> None:
        """Mark rows (``(A,)`` bool) as finished."""
        self.alive &= ~rows
        self.count = int(self.alive.sum())

    def advance(self) -> None:
        """Move every live ray into its next voxel; rays leaving the grid or reaching ``t_stop`` die.

        The grid exit is detected by distance (the exit boundary's ``t`` uses the same expression as
        the step), so no bounds test is needed.
        """
        if self.count < 0.6 * self.alive.numel():
            keep = torch.nonzero(self.alive).squeeze(1)
            for name in self._ROW_FIELDS:
                setattr(self, name, getattr(self, name)[keep])
        t_axis = torch.addcmul(self.offset, self.index, self.inv)
        t_next = t_axis.amin(dim=-1)
        cross = t_axis == t_next[:, None]  # ties cross together: a diagonal step
        self.index = torch.addcmul(self.index, self.step, cross)
        self.flat = self.flat + (cross * self.step) @ self.strides
        self.t_entry = t_next
        self.kill(~(t_next < self.t_stop))


def _with_trash(occupied_flat: Tensor) -> Tensor:
    """The flattened occupancy with one extra, never occupied, trash slot at the end."""
    return torch.cat([occupied_flat.to(torch.bool), occupied_flat.new_zeros(1, dtype=torch.bool)])


def _as_distances(max_distance: float | Tensor, count: int, device: torch.device) -> Tensor:
    return torch.as_tensor(max_distance, dtype=torch.float64, device=device).expand(count)


def first_hit(
    occupied: Tensor, grid: GridSpec, origins: Tensor, directions: Tensor, max_distance: float | Tensor
) -> tuple[Tensor, Tensor]:
    """The first occupied voxel along each ray.

    Args:
        occupied: ``(X, Y, Z)`` bool occupancy on ``grid``.
        grid: the voxel grid (ego frame, metres).
        origins: ``(R, 3)`` ray origins, metres; inside or outside the grid.
        directions: ``(R, 3)`` **unit** ray directions.
        max_distance: a number or ``(R,)`` tensor, metres: only voxels entered at
            ``t < max_distance`` are considered (the ray is the half-open segment
            ``[0, max_distance)``).

    Returns:
        ``hit_index``: ``(R, 3)`` int64 ``(i, j, k)`` of the first occupied voxel the ray traverses,
        ``-1`` in every column for rays without a hit.
        ``distance``: ``(R,)`` the entry distance of that voxel in metres (``0`` when the origin
        already lies inside it), ``inf`` for rays without a hit; float64 if ``directions`` is
        float64, else float32.
    """
    count, device = origins.shape[0], origins.device
    hit_index = torch.full((count, 3), -1, dtype=torch.int64, device=device)
    distance = torch.full((count,), torch.inf, dtype=torch.float64, device=device)
    out_dtype = torch.float64 if directions.dtype == torch.float64 else torch.float32
    if count == 0:
        return hit_index, distance.to(out_dtype)
    occ = _with_trash(occupied.reshape(-1))
    walk = _Walk(grid, origins, directions, _as_distances(max_distance, count, device))
    while len(walk):
        hit = occ[walk.voxels()]
        if hit.any():
            rows = torch.nonzero(hit).squeeze(1)
            hit_index[walk.ray[rows]] = walk.index[rows].to(torch.int64)
            distance[walk.ray[rows]] = walk.t_entry[rows]
            walk.kill(hit)
        if len(walk):
            walk.advance()
    return hit_index, distance.to(out_dtype)


def traversed_mask(grid: GridSpec, origins: Tensor, endpoints: Tensor) -> Tensor:
    """Every voxel that at least one segment ``origin -> endpoint`` passes through.

    A voxel is marked when the segment traverses it (positive length inside, see the module
    docstring), i.e. it is entered at ``t < |endpoint - origin|``, or when it contains the endpoint
    (half-open voxel convention of :class:`~occplug.geometry.GridSpec`), so the endpoint's voxel is
    always included when the endpoint lies in the grid. Parts of a segment outside the grid are
    ignored.

    Args:
        grid: the voxel grid.
        origins: ``(R, 3)`` segment starts, metres.
        endpoints: ``(R, 3)`` segment ends, metres.

    Returns:
        ``(X, Y, Z)`` bool.
    """
    device = origins.device
    voxels = math.prod(grid.shape)
    mask = torch.zeros(voxels + 1, dtype=torch.bool, device=device)  # + trash slot
    if origins.shape[0] == 0:
        return mask[:voxels].reshape(grid.shape)
    delta = endpoints.to(torch.float64) - origins.to(torch.float64)
    length = delta.norm(dim=-1)
    directions = delta / length.clamp_min(1e-300)[:, None]
    walk = _Walk(grid, origins, directions, length)
    while len(walk):
        mask[walk.voxels()] = True
        walk.advance()
    end_index = grid.coord_to_index(endpoints)
    inside = grid.index_in_bounds(end_index)
    strides = torch.tensor([grid.shape[1] * grid.shape[2], grid.shape[2], 1], device=device)
    mask[(end_index[inside] * strides).sum(-1)] = True
    return mask[:voxels].reshape(grid.shape)


def observed_mask(
    occupied: Tensor, grid: GridSpec, origins: Tensor, directions: Tensor, max_distance: float | Tensor
) -> Tensor:
    """Occ3D-style visibility: voxels a ray traverses up to and including its first occupied voxel.

    Each ray marks every voxel it traverses (entered at ``t < max_distance``) until it reaches an
    occupied voxel, which it marks too and then stops: everything behind the first occupied voxel
    is unobserved by that ray.

    Args:
        occupied: ``(X, Y, Z)`` bool occupancy on ``grid``.
        grid: the voxel grid.
        origins: ``(R, 3)`` sensor positions, metres.
        directions: ``(R, 3)`` unit directions.
        max_distance: a number or ``(R,)`` tensor, metres (e.g. the sensor range or the measured
            range of each ray).

    Returns:
        ``(X, Y, Z)`` bool.
    """
    count, device = origins.shape[0], origins.device
    voxels = math.prod(grid.shape)
    mask = torch.zeros(voxels + 1, dtype=torch.bool, device=device)  # + trash slot
    if count == 0:
        return mask[:voxels].reshape(grid.shape)
    occ = _with_trash(occupied.reshape(-1))
    walk = _Walk(grid, origins, directions, _as_distances(max_distance, count, device))
    while len(walk):
        flat = walk.voxels()
        mask[flat] = True
        hit = occ[flat]
        if hit.any():
            walk.kill(hit)
        if len(walk):
            walk.advance()
    return mask[:voxels].reshape(grid.shape)


# ----------------------------------------------------------------------------------------------
# Several grids at once, with exact empty-space skipping.


class RayHits(NamedTuple):
    """The first occupied voxel of every ray in each of ``G`` grids (see :func:`first_hits`).

    Attributes:
        index: ``(G, R, 3)`` int64 ``(i, j, k)`` of the first occupied voxel, ``-1`` in every
            column where the ray hits nothing in that grid.
        entry: ``(G, R)`` float64 distance (metres) at which the ray enters that voxel (``0`` if the
            origin lies inside it), ``inf`` without a hit.
        exit: ``(G, R)`` float64 distance at which the ray leaves that voxel through its far
            boundary (not limited by ``max_distance``), ``inf`` without a hit.
    """

    index: Tensor
    entry: Tensor
    exit: Tensor


def _dilate(mask: Tensor) -> Tensor:
    """Chebyshev dilation by one voxel (the 3 x 3 x 3 cube), separably along each axis."""
    out = mask
    for dim in range(3):
        grown = out.clone()
        n = out.shape[dim]
        grown.narrow(dim, 1, n - 1).logical_or_(out.narrow(dim, 0, n - 1))
        grown.narrow(dim, 0, n - 1).logical_or_(out.narrow(dim, 1, n - 1))
        out = grown
    return out


def clearance(occupied: Tensor, cap: int = 16) -> Tensor:
    """Chebyshev distance, in voxels, from every voxel to the nearest occupied voxel.

    Every voxel ``w`` with ``max(|w - v|) < clearance[v]`` is free, so a ray inside voxel ``v`` can
    skip the free cube of half-width ``clearance[v] - 1`` around it. Space outside the grid counts
    as free.

    Args:
        occupied: ``(X, Y, Z)`` bool.
        cap: the largest value computed; voxels farther from any occupied voxel get ``cap``.

    Returns:
        ``(X, Y, Z)`` int64: ``0`` on occupied voxels, ``1..cap`` elsewhere.
    """
    reached = occupied.to(torch.bool)
    dist = torch.where(reached, 0, cap).to(torch.int64)
    for radius in range(1, cap):
        if bool(reached.all()):
            break
        grown = _dilate(reached)
        dist = torch.where(grown & ~reached, radius, dist)
        reached = grown
    return dist


class _SkipWalk(_Walk):
    """A :class:`_Walk` over ``G`` grids that jumps across free space.

    Each row keeps ``pending`` (``(A, G)`` bool): the grids in which the ray has not hit yet. A jump
    from voxel ``v`` with clearance ``c`` moves to the first voxel outside the free cube of
    half-width ``c - 1`` around ``v``. The voxel reached is computed from the same boundary
    distances ``t = offset + index * inv`` the one-voxel step compares, counting on every axis the
    boundaries with ``t <= T`` (``T`` the cube's exit distance), so a jump ends exactly where the
    equivalent sequence of single steps (:meth:`_Walk.advance`) would, ties included; ``c = 1`` is
    one single step.
    """

    _ROW_FIELDS = (*_Walk._ROW_FIELDS, "pending")

    def __init__(self, grid: GridSpec, origins: Tensor, directions: Tensor, max_distance: Tensor, grids: int) -> None:
        super().__init__(grid, origins, directions, max_distance)
        self.pending = torch.ones(self.ray.numel(), grids, dtype=torch.bool, device=origins.device)

    def exit_distance(self, rows: Tensor) -> Tensor:
        """``(n,)`` the distance at which each of ``rows`` leaves its current voxel."""
        return torch.addcmul(self.offset[rows], self.index[rows], self.inv[rows]).amin(dim=-1)

    def jump(self, clear: Tensor) -> None:
        """Advance every live row past the free cube given by ``clear`` (``(A,)`` int64, ``>= 1``)."""
        if self.count < 0.6 * self.alive.numel():
            keep = torch.nonzero(self.alive).squeeze(1)
            for name in self._ROW_FIELDS:
                setattr(self, name, getattr(self, name)[keep])
            clear = clear[keep]
        span = clear.to(torch.float64)[:, None]  # c: the axis leaving the cube crosses c boundaries
        far = torch.addcmul(self.index, self.step, span - 1)  # last voxel of the cube on each axis
        t_jump = torch.addcmul(self.offset, far, self.inv).amin(dim=-1)  # the cube's exit distance
        # boundaries crossed on each axis by t_jump: estimate by division, then settle exactly with
        # the comparison the single step uses (rounding moves the estimate by at most one)
        moving = self.step != 0
        u = (t_jump[:, None] - self.offset) / torch.where(moving, self.inv, torch.ones_like(self.inv))
        crossed = torch.where(self.step > 0, torch.floor(u) - self.index, self.index - torch.ceil(u)) + 1
        crossed = torch.where(moving, crossed.clamp(min=torch.zeros_like(span), max=span), 0.0)
        ahead = torch.addcmul(self.offset, torch.addcmul(self.index, self.step, crossed), self.inv)
        crossed = crossed + (moving & (ahead <= t_jump[:, None]) & (crossed < span)).to(torch.float64)
        behind = torch.addcmul(self.offset, torch.addcmul(self.index, self.step, crossed - 1), self.inv)
        crossed = crossed - (moving & (crossed > 0) & (behind > t_jump[:, None])).to(torch.float64)
        moved = self.step * crossed
        self.index = self.index + moved
        self.flat = self.flat + moved @ self.strides
        self.t_entry = t_jump
        self.kill(~(t_jump < self.t_stop))


def _use_numba(kernel: str, device: torch.device, grids: int) -> bool:
    from . import raycast_numba

    if kernel == "torch":
        return False
    if kernel == "numba":
        if device.type != "cpu" or not raycast_numba.available():
            why = "numba is not installed (pip install occplug[fast])" if device.type == "cpu" else "CPU tensors only"
            raise ValueError(f"first_hits: kernel 'numba' needs {why}")
        return True
    if kernel != "auto":
        raise ValueError(f"first_hits: kernel must be 'auto', 'torch' or 'numba', got {kernel!r}")
    return device.type == "cpu" and grids <= raycast_numba.MAX_GRIDS and raycast_numba.available()


def first_hits(
    occupied: Tensor,
    grid: GridSpec,
    origins: Tensor,
    directions: Tensor,
    max_distance: float | Tensor,
    skip: bool = True,
    kernel: Literal["auto", "torch", "numba"] = "auto",
) -> RayHits:
    """:func:`first_hit` through ``G`` grids at once, with entry and exit distances.

    Each ray is walked once and stops when it has hit in every grid, so casting the same rays
    through a prediction and its ground truth costs little more than one cast. With ``skip`` the
    walk jumps across free space using :func:`clearance` of the union of the grids; the jumps land
    exactly where single steps would (see :class:`_SkipWalk`), so the results do not depend on
    ``skip`` — only the speed does.

    Args:
        occupied: ``(G, X, Y, Z)`` bool occupancy of ``G`` grids sharing ``grid``.
        grid: the voxel grid (ego frame, metres).
        origins: ``(R, 3)`` ray origins, metres; inside or outside the grid.
        directions: ``(R, 3)`` **unit** ray directions.
        max_distance: a number or ``(R,)`` tensor, metres: only voxels entered at
            ``t < max_distance`` are considered.
        skip: jump across free space (same results, faster in open scenes; the torch walk only).
        kernel: ``torch``: the pure-PyTorch walk (the reference, any device); ``numba``: the compiled
            per-ray loop of :mod:`occplug.geometry.raycast_numba` (CPU tensors, needs ``numba``; the
            same results bit for bit); ``auto``: ``numba`` for CPU tensors when it is installed, else
            ``torch``.

    Returns:
        :class:`RayHits`; ``index[g]`` and ``entry[g]`` equal :func:`first_hit` on ``occupied[g]``.
    """
    grids, count, device = occupied.shape[0], origins.shape[0], origins.device
    index = torch.full((grids, count, 3), -1, dtype=torch.int64, device=device)
    entry = torch.full((grids, count), torch.inf, dtype=torch.float64, device=device)
    exit_ = entry.clone()
    if count == 0 or grids == 0:
        return RayHits(index, entry, exit_)
    if _use_numba(kernel, device, grids):
        from .raycast_numba import first_hits_numba

        walk = _Walk(grid, origins, directions, _as_distances(max_distance, count, device))
        first_hits_numba(occupied.to(torch.bool), walk, index, entry, exit_)
        return RayHits(index, entry, exit_)
    flat_occ = occupied.reshape(grids, -1).to(torch.bool)
    # one lookup table: bit g = occupied in grid g, the rest = clearance of the union; trash slot last
    union = flat_occ.any(0).reshape(grid.shape)
    clear = clearance(union) if skip else torch.ones(grid.shape, dtype=torch.int64, device=device)
    bits = (flat_occ.to(torch.int64) << torch.arange(grids, device=device)[:, None]).sum(0)
    table = torch.cat([(clear.reshape(-1) << grids) | bits, torch.tensor([1 << grids], device=device)])
    grid_bits = 1 << torch.arange(grids, device=device)
    walk = _SkipWalk(grid, origins, directions, _as_distances(max_distance, count, device), grids)
    while len(walk):
        code = table[walk.voxels()]
        hit = ((code[:, None] & grid_bits) != 0) & walk.pending
        if hit.any():
            rows, which = torch.nonzero(hit, as_tuple=True)
            rays = walk.ray[rows]
            index[which, rays] = walk.index[rows].to(torch.int64)
            entry[which, rays] = walk.t_entry[rows]
            exit_[which, rays] = walk.exit_distance(rows)
            walk.pending &= ~hit
            walk.kill(~walk.pending.any(dim=1))
        if len(walk):
            walk.jump((code >> grids).clamp_min(1))
    return RayHits(index, entry, exit_)
