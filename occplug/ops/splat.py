"""Fast splat (voxel pooling) of frustum features, with per-geometry plans (the BEVPoolv2 idea).

A lift-splat view transform places, for every camera ``n``, depth bin ``d`` and feature cell
``(r, c)``, the product ``depth[n, d, r, c] * context[n, :, r, c]`` in the voxel that holds the
point, and sums per voxel. Which voxel a point lands in depends only on geometry (calibration,
image augmentation, feature-map size, stride, depth bins, grid), never on the features, so the
whole mapping can be prepared once per geometry (a :class:`SplatPlan`) and reused while the
geometry is unchanged (:class:`SplatPlanCache`, keyed by :func:`geometry_key`).

The pooling itself never builds the ``D x C`` products. With ``A`` the sparse
``(occupied voxels) x (cells)`` matrix whose entry ``(v, cell)`` is the sum of the depth
probabilities of that cell's points inside voxel ``v``::

    out[v, :] = sum over points p in v of depth[p] * context[cell(p), :] = (A @ context)[v, :]

so one sparse-matrix product (CSR, pure PyTorch) replaces the ``(N*D*h*w, C)`` frustum tensor and
its ``index_add_``. The gradients are exact and explicit (:class:`_SplatOuter`):
``d context = A^T @ grad`` and ``d A[v, cell] = <grad[v, :], context[cell, :]>`` (a sampled
dense-dense product over the non-zeros only), which flows back to each point's depth probability.

Everything is vectorised (no Python loop over points; one loop over batch items); the
reference to match is :func:`occplug.components.view_transforms.splat`. A CUDA kernel may be
added beside this path later, never instead of it.
"""

from __future__ import annotations

import hashlib
import math
import warnings
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

__all__ = ["SplatPlan", "SplatPlanCache", "build_splat_plan", "geometry_key", "splat_outer"]


# ----------------------------------------------------------------------------- plan
@dataclass(frozen=True, eq=False)
class SplatPlan:
    """The precomputed pooling structure of one sample's frustum (see :func:`build_splat_plan`).

    Points are the ``P = N*D*h*w`` entries of a ``(N, D, h, w)`` depth tensor; a point's *cell* is
    ``(n, r, c)``, numbered ``n*h*w + r*w + c`` (``M = N*h*w`` cells). A *pair* is a distinct
    (voxel, cell) combination holding at least one point (``nnz`` pairs); pairs are sorted by voxel
    then cell, which is exactly CSR order of the ``(V_occ, M)`` matrix ``A``.

    Attributes:
        shape: ``(N, D, h, w)`` of the depth tensor the plan was built for.
        num_voxels: ``V``, voxels of the output grid (one sample).
        voxels: ``(V_occ,)`` int64 sorted ids in ``[0, V)`` of the voxels that receive a point.
        crow: ``(V_occ + 1,)`` CSR row pointers of ``A`` (int32 when it fits, else int64).
        col: ``(nnz,)`` cell of each pair (same dtype as ``crow``).
        point: ``(K,)`` int64 flat index into the ``(N, D, h, w)`` depth tensor of every point
            inside the grid (``K <= P``), ordered by pair.
        pair: ``(K,)`` int64 pair of each point, or ``None`` when every pair holds exactly one
            point (then point ``k`` is pair ``k``).
        t_crow: ``(M + 1,)`` CSR row pointers of ``A^T`` (cells x occupied voxels).
        t_col: ``(nnz,)`` occupied-voxel row of ``A`` for each entry of ``A^T``.
        t_perm: ``(nnz,)`` int64: entry ``j`` of ``A^T`` is pair ``t_perm[j]``.
    """

    shape: tuple[int, int, int, int]
    num_voxels: int
    voxels: Tensor
    crow: Tensor
    col: Tensor
    point: Tensor
    pair: Tensor | None
    t_crow: Tensor
    t_col: Tensor
    t_perm: Tensor

    @property
    def num_cells(self) -> int:
        """``M = N*h*w``."""
        n, _, h, w = self.shape
        return n * h * w

    @property
    def nnz(self) -> int:
        """Number of (voxel, cell) pairs."""
        return int(self.col.numel())

    @property
    def num_points_inside(self) -> int:
        """``K``: points that land inside the grid."""
        return int(self.point.numel())

    def nbytes(self) -> int:
        """Memory held by the plan's tensors, bytes."""
        tensors = [self.voxels, self.crow, self.col, self.point, self.t_crow, self.t_col, self.t_perm]
        if self.pair is not None:
            tensors.append(self.pair)
        return sum(t.numel() * t.element_size() for t in tensors)

    def pair_values(self, depth_flat: Tensor) -> Tensor:
        """``(nnz,)`` values of ``A``: the summed depth of each pair's points, from ``(P,)`` ``depth_flat``."""
        vals = depth_flat[self.point]
        if self.pair is None:
            return vals
        return vals.new_zeros(self.nnz).index_add_(0, self.pair, vals)

    def matrix(self, values: Tensor) -> Tensor:
        """``A`` as a sparse CSR ``(V_occ, M)`` tensor with the given ``(nnz,)`` values."""
        return _csr(self.crow, self.col, values, (int(self.voxels.numel()), self.num_cells))

    def matrix_t(self, values: Tensor) -> Tensor:
        """``A^T`` as a sparse CSR ``(M, V_occ)`` tensor, given ``A``'s ``(nnz,)`` values."""
        return _csr(self.t_crow, self.t_col, values[self.t_perm], (self.num_cells, int(self.voxels.numel())))


def _csr(crow: Tensor, col: Tensor, values: Tensor, size: tuple[int, int]) -> Tensor:
    with warnings.catch_warnings():  # torch flags sparse CSR as "beta" once per process
        warnings.filterwarnings("ignore", message=".*Sparse CSR tensor support is in beta.*")
        return torch.sparse_csr_tensor(crow, col, values, size=size, check_invariants=False)


def _csr_rows(rows: Tensor, num_rows: int, dtype: torch.dtype) -> Tensor:
    """``(num_rows + 1,)`` CSR row pointers of sorted row ids."""
    crow = torch.zeros(num_rows + 1, dtype=torch.int64, device=rows.device)
    crow[1:] = torch.bincount(rows, minlength=num_rows).cumsum(0)
    return crow.to(dtype)


def build_splat_plan(index: Tensor, num_voxels: int) -> SplatPlan:
    """Prepare the pooling of one sample's frustum into ``num_voxels`` voxels.

    Args:
        index: ``(N, D, h, w)`` int64 voxel of every (camera, depth bin, cell) point, in
            ``[0, num_voxels)``, or ``-1`` for a point outside the grid (dropped).
        num_voxels: ``V``.

    Returns:
        A :class:`SplatPlan` on ``index``'s device. Cost: one sort of the ``K`` points inside
        the grid and one of the ``nnz`` pairs; nothing depends on feature values.
    """
    if index.dim() != 4:
        raise ValueError(f"build_splat_plan: expected index (N, D, h, w), got shape {tuple(index.shape)}")
    n, d, h, w = (int(s) for s in index.shape)
    hw, cells = h * w, n * h * w
    device = index.device
    flat = index.reshape(-1).long()
    if flat.numel() and (int(flat.max()) >= num_voxels or int(flat.min()) < -1):
        raise ValueError(f"build_splat_plan: voxel index outside [-1, {num_voxels})")
    point = torch.nonzero(flat >= 0).squeeze(1)  # (K,) flat point ids
    voxel = flat[point]
    cell = (point // (d * hw)) * hw + point % hw
    key = voxel * cells + cell
    key, order = torch.sort(key, stable=True)
    point = point[order]
    pair_key, counts = torch.unique_consecutive(key, return_counts=True)
    nnz = int(pair_key.numel())
    pair = None if nnz == int(point.numel()) else torch.repeat_interleave(torch.arange(nnz, device=device), counts)
    row_voxel = pair_key // cells
    col = pair_key % cells
    voxels, row = torch.unique_consecutive(row_voxel, return_inverse=True)
    occ = int(voxels.numel())
    itype = torch.int32 if max(nnz, occ, cells) < 2**31 - 1 else torch.int64
    crow = _csr_rows(row, occ, itype)
    # A^T: entries sorted by (cell, voxel row); pairs are sorted by (row, cell), so a stable sort on cell suffices.
    t_order = torch.sort(col, stable=True)[1]
    t_crow = _csr_rows(col[t_order], cells, itype)
    return SplatPlan(
        shape=(n, d, h, w),
        num_voxels=int(num_voxels),
        voxels=voxels,
        crow=crow,
        col=col.to(itype),
        point=point,
        pair=pair,
        t_crow=t_crow,
        t_col=row[t_order].to(itype),
        t_perm=t_order,
    )


# ----------------------------------------------------------------------------- cache
def geometry_key(*tensors: Tensor, **static: object) -> str:
    """An exact fingerprint of the tensors and static values that determine a plan.

    Every tensor contributes its dtype, shape, device and raw bytes (copied to the host: meant
    for small calibration tensors), every static value its ``repr``; the digest is a BLAKE2b
    hash of all of it, so any changed bit of an extrinsic, intrinsic or augmentation matrix gives
    another key. Float geometry should be cast to the dtype it is used in (e.g. ``.float()``)
    before fingerprinting, so that two inputs giving the same points share a key.
    """
    h = hashlib.blake2b(digest_size=20)
    for t in tensors:
        t = t.detach()
        h.update(f"{t.dtype}|{tuple(t.shape)}|{t.device}|".encode())
        h.update(t.contiguous().reshape(-1).view(torch.uint8).cpu().numpy().tobytes())
    for name in sorted(static):
        h.update(f"|{name}={static[name]!r}".encode())
    return h.hexdigest()


class SplatPlanCache:
    """A small least-recently-used map ``geometry key -> SplatPlan``.

    Args:
        max_entries: plans kept (a nuScenes-size plan holds a few MB); the least recently used
            is dropped beyond it.

    Attributes:
        hits, misses: lookups served from the cache / built.
    """

    def __init__(self, max_entries: int = 16) -> None:
        if max_entries < 1:
            raise ValueError(f"SplatPlanCache max_entries must be >= 1, got {max_entries}")
        self.max_entries = int(max_entries)
        self._plans: OrderedDict[str, SplatPlan] = OrderedDict()
        self.hits = 0
        self.misses = 0

    def __len__(self) -> int:
        return len(self._plans)

    def __contains__(self, key: str) -> bool:
        return key in self._plans

    def get(self, key: str) -> SplatPlan | None:
        """The plan stored under ``key`` (marked recently used), or ``None``; counts a hit or a miss."""
        plan = self._plans.get(key)
        if plan is None:
            self.misses += 1
            return None
        self._plans.move_to_end(key)
        self.hits += 1
        return plan

    def put(self, key: str, plan: SplatPlan) -> None:
        """Store ``plan`` under ``key``, dropping the least recently used plan beyond ``max_entries``."""
        self._plans[key] = plan
        self._plans.move_to_end(key)
        while len(self._plans) > self.max_entries:
            self._plans.popitem(last=False)

    def get_or_build(self, key: str, build: Callable[[], SplatPlan]) -> SplatPlan:
        """The plan under ``key``, building and storing it with ``build()`` on a miss."""
        plan = self.get(key)
        if plan is None:
            plan = build()
            self.put(key, plan)
        return plan

    def clear(self) -> None:
        """Forget every plan (counters are kept)."""
        self._plans.clear()

    def __getstate__(self) -> dict:  # pickling / deepcopy (e.g. a teacher copy) starts with an empty cache
        return {"max_entries": self.max_entries, "_plans": OrderedDict(), "hits": 0, "misses": 0}


# ----------------------------------------------------------------------------- pooling
class _SplatOuter(torch.autograd.Function):
    """``(B, N, D, h, w)`` depth x ``(B, N, h, w, C)`` context -> ``(B, C, V)``, with explicit gradients."""

    @staticmethod
    def forward(ctx, depth: Tensor, context: Tensor, plans: tuple[SplatPlan, ...]) -> Tensor:  # type: ignore[override]
        b, c = depth.shape[0], context.shape[-1]
        v = plans[0].num_voxels
        depth_flat = depth.reshape(b, -1)
        context_cl = context.reshape(b, -1, c)
        out = depth.new_zeros(b, c, v)
        values = []
        for i, plan in enumerate(plans):
            vals = plan.pair_values(depth_flat[i])
            values.append(vals)
            if plan.nnz == 0:
                continue
            pooled = plan.matrix(vals) @ context_cl[i]  # (V_occ, C)
            out[i].index_copy_(1, plan.voxels, pooled.t())
        ctx.plans = plans
        ctx.save_for_backward(context_cl, *values)
        ctx.depth_shape = depth.shape
        ctx.context_shape = context.shape
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, Tensor | None, None]:  # type: ignore[override]
        context_cl, *values = ctx.saved_tensors
        plans: tuple[SplatPlan, ...] = ctx.plans
        want_depth, want_context = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        b = len(plans)
        grad = grad.contiguous()
        grad_depth = grad.new_zeros(b, math.prod(ctx.depth_shape[1:])) if want_depth else None
        grad_context = grad.new_zeros(context_cl.shape) if want_context else None
        for i, plan in enumerate(plans):
            if plan.nnz == 0:
                continue
            g_occ = grad[i].index_select(1, plan.voxels).t().contiguous()  # (V_occ, C)
            if want_context:
                grad_context[i] = plan.matrix_t(values[i]) @ g_occ  # (M, C)
            if want_depth:
                # d out[v] / d A[v, cell] = context[cell]: one dot product per non-zero.
                sampled = torch.sparse.sampled_addmm(
                    plan.matrix(values[i]), g_occ, context_cl[i].t().contiguous(), beta=0.0
                )
                g_pair = sampled.values()
                grad_depth[i, plan.point] = g_pair if plan.pair is None else g_pair[plan.pair]
        return (
            grad_depth.view(ctx.depth_shape) if want_depth else None,
            grad_context.view(ctx.context_shape) if want_context else None,
            None,
        )


def splat_outer(depth: Tensor, context: Tensor, plans: Sequence[SplatPlan]) -> Tensor:
    """Sum-pool ``depth x context`` frustum features into voxels, per a plan for each batch item.

    Equal (up to float summation order) to building the ``(B, N, D, h, w, C)`` products and
    :func:`~occplug.components.view_transforms.splat`-ing them with the plan's voxel index, but
    without the products: see the module docstring.

    Args:
        depth: ``(B, N, D, h, w)`` floating weights per point (e.g. depth probabilities).
        context: ``(B, N, C, h, w)`` floating features per cell, same dtype and device.
        plans: ``B`` plans (:func:`build_splat_plan`) of shape ``(N, D, h, w)`` on the same
            device, all for the same ``V``.

    Returns:
        ``(B, C, V)`` in ``depth``'s dtype: ``out[b, :, v]`` sums ``depth[b, n, d, r, c] *
        context[b, n, :, r, c]`` over the points of plan ``b`` inside voxel ``v`` (zero for an
        empty voxel). Differentiable in ``depth`` and ``context`` (first order).
    """
    if depth.dim() != 5 or context.dim() != 5:
        raise ValueError(f"splat_outer: expected depth (B, N, D, h, w) and context (B, N, C, h, w), got "
                         f"{tuple(depth.shape)} and {tuple(context.shape)}")
    b, n, d, h, w = depth.shape
    if context.shape[0] != b or context.shape[1] != n or context.shape[3:] != (h, w):
        raise ValueError(f"splat_outer: context {tuple(context.shape)} does not match depth {tuple(depth.shape)}")
    if len(plans) != b:
        raise ValueError(f"splat_outer: {len(plans)} plans for a batch of {b}")
    if any(p.shape != (n, d, h, w) for p in plans) or len({p.num_voxels for p in plans}) != 1:
        raise ValueError(f"splat_outer: every plan must be for depth ({n}, {d}, {h}, {w}) and one grid")
    if depth.dtype != context.dtype:
        raise ValueError(f"splat_outer: depth is {depth.dtype} but context is {context.dtype}")
    context_cl = context.permute(0, 1, 3, 4, 2)  # (B, N, h, w, C): one row per cell
    return _SplatOuter.apply(depth.contiguous(), context_cl.contiguous(), tuple(plans))
