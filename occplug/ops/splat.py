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

Per-point features (any ``(B, N, D, C, h, w)`` feature per (camera, depth bin, cell), not only
the outer product) pool through the same plan (:class:`_SplatPoints`): the features of the points
inside the grid are gathered in plan order, which is sorted by voxel, and summed per voxel by one
sparse ``(V_occ, K)`` matrix of ones; the gradient of a point is its voxel's output gradient.

Everything is vectorised (no Python loop over points; one loop over batch items); the
reference to match is :func:`splat` (``index_add_`` over every frustum point). A CUDA kernel
may be added beside this path later, never instead of it.

:class:`FrustumSplatter` is the public front: it computes the frustum of a batch's cameras
(any monotone depth centres, shared or per camera), maps it to the cells of a 3D or BEV
:class:`~occplug.geometry.GridSpec` (contracted grids included, or through a custom
point -> cell hook), caches the plans per geometry and runs either path.
"""

from __future__ import annotations

import hashlib
import math
import warnings
from collections import OrderedDict
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Literal

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from occplug.constraints import check_choices
from occplug.geometry import GridSpec, pixel_centers, unproject_from_image

__all__ = [
    "FrustumSplatter",
    "PointToIndex",
    "SplatPlan",
    "SplatPlanCache",
    "build_splat_plan",
    "feature_cell_centers",
    "frustum_points",
    "geometry_key",
    "splat",
    "splat_outer",
    "splat_points",
]

#: A point -> cell hook: ``(..., 3)`` float64 ego-frame points to ``(..., 3)`` int64 ``(i, j, k)``
#: cells of the target grid; cells outside ``[0, X) x [0, Y) x [0, Z)`` are dropped.
PointToIndex = Callable[[Tensor], Tensor]


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

    @cached_property
    def point_row(self) -> Tensor:
        """``(K,)`` int64 occupied-voxel row (into :attr:`voxels`) of every inside point, in :attr:`point` order."""
        occ = int(self.voxels.numel())
        pair_row = torch.repeat_interleave(torch.arange(occ, device=self.crow.device), self.crow.long().diff())
        return pair_row if self.pair is None else pair_row[self.pair]

    @cached_property
    def point_crow(self) -> Tensor:
        """``(V_occ + 1,)`` CSR row pointers of the ``(V_occ, K)`` point -> voxel matrix (per-point path)."""
        return _csr_rows(self.point_row, int(self.voxels.numel()), self.crow.dtype)

    def point_matrix(self, dtype: torch.dtype) -> Tensor:
        """The sparse CSR ``(V_occ, K)`` matrix of ones summing the inside points (in :attr:`point` order) per voxel."""
        k = self.num_points_inside
        col = torch.arange(k, device=self.point.device, dtype=self.crow.dtype)
        ones = torch.ones(k, dtype=dtype, device=self.point.device)
        return _csr(self.point_crow, col, ones, (int(self.voxels.numel()), k))


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
        raise ValueError(
            f"splat_outer: expected depth (B, N, D, h, w) and context (B, N, C, h, w), got "
            f"{tuple(depth.shape)} and {tuple(context.shape)}"
        )
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


class _SplatPoints(torch.autograd.Function):
    """``(B, N*D, C, h*w)`` per-point features -> ``(B, C, V)``; the gradient of a point is its voxel's."""

    @staticmethod
    def forward(ctx, features: Tensor, plans: tuple[SplatPlan, ...], hw: int) -> Tensor:  # type: ignore[override]
        b, _, c, _ = features.shape
        out = features.new_zeros(b, c, plans[0].num_voxels)
        for i, plan in enumerate(plans):
            if plan.nnz == 0:
                continue
            rows = features[i][plan.point // hw, :, plan.point % hw]  # (K, C), plan order = sorted by voxel
            pooled = plan.point_matrix(features.dtype) @ rows  # (V_occ, C)
            out[i].index_copy_(1, plan.voxels, pooled.t())
        ctx.plans, ctx.hw, ctx.shape = plans, hw, features.shape
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None, None]:  # type: ignore[override]
        plans: tuple[SplatPlan, ...] = ctx.plans
        hw = ctx.hw
        grad_features = grad.new_zeros(ctx.shape)
        for i, plan in enumerate(plans):
            if plan.nnz == 0:
                continue
            g_occ = grad[i].index_select(1, plan.voxels).t()  # (V_occ, C)
            grad_features[i][plan.point // hw, :, plan.point % hw] = g_occ.index_select(0, plan.point_row)
        return grad_features, None, None


def splat_points(features: Tensor, plans: Sequence[SplatPlan]) -> Tensor:
    """Sum-pool per-point frustum features into voxels, per a plan for each batch item.

    Equal (up to float summation order) to :func:`splat` of the features made channels-last with
    the plan's voxel index, but only the points inside the grid are read.

    Args:
        features: ``(B, N, D, C, h, w)`` floating features of every (camera, depth bin, cell)
            point (a channels-last ``(B, N, D, h, w, C)`` tensor permuted to this shape works too).
        plans: ``B`` plans (:func:`build_splat_plan`) of shape ``(N, D, h, w)``, one ``V``.

    Returns:
        ``(B, C, V)`` in ``features``' dtype: ``out[b, :, v]`` sums ``features[b, n, d, :, r, c]``
        over the points of plan ``b`` inside voxel ``v``. Differentiable in ``features``.
    """
    if features.dim() != 6:
        raise ValueError(f"splat_points: expected features (B, N, D, C, h, w), got shape {tuple(features.shape)}")
    b, n, d, c, h, w = features.shape
    if len(plans) != b:
        raise ValueError(f"splat_points: {len(plans)} plans for a batch of {b}")
    if any(p.shape != (n, d, h, w) for p in plans) or len({p.num_voxels for p in plans}) != 1:
        raise ValueError(f"splat_points: every plan must be for points ({n}, {d}, {h}, {w}) and one grid")
    return _SplatPoints.apply(features.reshape(b, n * d, c, h * w), tuple(plans), h * w)


def splat(features: Tensor, index: Tensor, num_voxels: int) -> Tensor:
    """Sum-pool point features into voxels (the naive, reference splat).

    Args:
        features: ``(M, C)`` features of ``M`` points.
        index: ``(M,)`` int64 voxel of each point in ``[0, num_voxels)``, or ``-1`` to drop it.
        num_voxels: number of output voxels.

    Returns:
        ``(num_voxels, C)``: for every voxel, the sum of the features of the points in it
        (zero for an empty voxel); differentiable with respect to ``features``.
    """
    out = features.new_zeros(num_voxels + 1, features.shape[1])
    dump = torch.where(index < 0, torch.full_like(index, num_voxels), index)  # dropped points go to a spare row
    return out.index_add_(0, dump, features)[:num_voxels]


# ----------------------------------------------------------------------------- frustum geometry
def feature_cell_centers(h: int, w: int, stride: int, device: torch.device | str | None = None) -> Tensor:
    """``(h, w, 2)`` float32 pixel ``(u, v)`` of each feature cell's centre: ``s*c + (s-1)/2``, ``s*r + (s-1)/2``."""
    return pixel_centers(h, w, device=device) * stride + (stride - 1) / 2.0


def _depths_per_camera(depths: Tensor, b: int, n: int) -> Tensor:
    """``(D,)``, ``(N, D)`` or ``(B, N, D)`` depth centres -> a ``(B, N, D)`` float32 view."""
    if (
        depths.dim() not in (1, 2, 3)
        or (depths.dim() >= 2 and depths.shape[-2] != n)
        or (depths.dim() == 3 and depths.shape[0] != b)
    ):
        raise ValueError(f"depth centres must be (D,), (N, D) or (B, N, D) for B={b}, N={n}; got {tuple(depths.shape)}")
    return depths.float().expand(b, n, depths.shape[-1])


def frustum_points(
    batch: Any, h: int, w: int, stride: int, depths: Tensor, dtype: torch.dtype = torch.float32
) -> Tensor:
    """Ego-frame points of every feature cell centre at every depth.

    Args:
        batch: supplies ``intrinsics`` ``(B, N, 3, 3)``, ``cam_to_ego`` ``(B, N, 4, 4)`` and
            ``img_aug`` ``(B, N, 3, 3)`` (a :class:`~occplug.data.Batch` or anything with those).
        h, w: feature map size; stride: pixels per feature cell.
        depths: camera-frame z values, metres: ``(D,)`` for every camera, ``(N, D)`` per camera or
            ``(B, N, D)`` per sample and camera.
        dtype: what the unprojection computes in. Voxel assignment uses float64: in float32 a
            point within an ulp of a voxel face lands on either side depending on the matmul
            kernel, so an exported graph (another runtime, another CPU) could move it.

    Returns:
        ``(B, N, D, h, w, 3)`` ``dtype`` ego-frame points: cell ``(r, c)``'s centre
        (:func:`feature_cell_centers`) unprojected through ``img_aug @ intrinsics`` at depth ``depths[..., d]``.
    """
    b, n = batch.cam_to_ego.shape[:2]
    z = _depths_per_camera(depths, b, n)
    d = z.shape[-1]
    uv = feature_cell_centers(h, w, stride, device=depths.device).to(dtype).expand(d, h, w, 2).reshape(1, 1, -1, 2)
    pts = unproject_from_image(
        uv.expand(b, n, -1, 2),
        z.to(dtype)[..., None, None].expand(b, n, d, h, w).reshape(b, n, -1),
        batch.intrinsics.to(dtype),
        batch.cam_to_ego.to(dtype),
        batch.img_aug.to(dtype),
    )
    return pts.view(b, n, d, h, w, 3)


def _no_autocast(device: torch.device) -> AbstractContextManager:
    """Geometry and pooling run in float32 even under mixed precision (bf16 would move points by centimetres)."""
    return torch.autocast(device_type=device.type, enabled=False)


def _pool_dtype(t: Tensor) -> Tensor:
    """Half-precision inputs are pooled in float32 (sums of many bf16 terms drift); float32/64 stay."""
    return t.float() if t.dtype in (torch.float16, torch.bfloat16) else t


# ----------------------------------------------------------------------------- the public splatter
class FrustumSplatter:
    """Splats frustum features of a batch's cameras into a 3D or BEV grid, with cached plans.

    A frustum point is a feature cell ``(r, c)`` of camera ``n`` at depth centre ``d``: the cell
    centre (:func:`feature_cell_centers`) unprojected through ``img_aug @ intrinsics`` and
    ``cam_to_ego`` (:func:`frustum_points`, in float64). ``point_to_index`` maps it to a cell ``(i, j, k)`` of
    ``grid`` (default: :meth:`GridSpec.coord_to_index`, which contracts x and y on a contracted
    grid, so far points land in the border cells); cells outside the grid are dropped. For a BEV
    target the cells ``(i, j, k)`` of one column sum into BEV cell ``(i, j)`` (``k`` must still
    lie in ``[0, Z)``: the grid's z range bounds what is pooled).

    Two kinds of features:

    * :meth:`splat_outer`: weights ``(B, N, D, h, w)`` (e.g. depth probabilities) times
      per-cell context ``(B, N, C, h, w)``, never building the products (:func:`splat_outer`);
    * :meth:`splat_points`: arbitrary per-point features ``(B, N, D, C, h, w)`` (:func:`splat_points`).

    With ``mode="fast"`` the (camera, depth, cell) -> voxel structure of each batch item is built
    once per geometry (its ``intrinsics``, ``cam_to_ego``, ``img_aug``, depth centres, feature-map
    size) and kept in :attr:`plan_cache`; ``mode="reference"`` runs the naive :func:`splat` over all
    points instead (same values up to float summation order). Half-precision inputs are pooled in float32.

    Args:
        grid: the target grid (metric or contracted).
        image_stride: image pixels per feature cell.
        bev: pool into ``(X, Y)`` instead of ``(X, Y, Z)``.
        point_to_index: optional :data:`PointToIndex` hook replacing the grid's own indexing; it
            must be a pure function of the points (plans are cached). Setting it clears the cache.
        mode: ``"fast"`` or ``"reference"``.
        max_plans: plans kept in the cache.

    Output of both splats: ``(B, C, X, Y, Z)`` (or ``(B, C, X, Y)`` for BEV) in the ego frame on
    ``grid``, float32 for half-precision inputs, else the inputs' dtype.
    """

    def __init__(
        self,
        grid: GridSpec,
        image_stride: int,
        bev: bool = False,
        point_to_index: PointToIndex | None = None,
        mode: Literal["fast", "reference"] = "fast",
        max_plans: int = 16,
    ) -> None:
        check_choices(FrustumSplatter.__init__, "splat", mode=mode)
        if int(image_stride) < 1:
            raise ValueError(f"image_stride must be >= 1, got {image_stride}")
        self.grid = grid
        self.image_stride = int(image_stride)
        self.bev = bool(bev)
        self.mode = mode
        #: geometry key -> :class:`SplatPlan` of one batch item (never part of a state dict).
        self.plan_cache = SplatPlanCache(max_plans)
        self._point_to_index = point_to_index

    @property
    def point_to_index(self) -> PointToIndex | None:
        """The point -> cell hook (``None``: the grid's :meth:`~GridSpec.coord_to_index`)."""
        return self._point_to_index

    @point_to_index.setter
    def point_to_index(self, hook: PointToIndex | None) -> None:
        self._point_to_index = hook
        self.plan_cache.clear()  # plans made with the old hook would be stale

    @property
    def out_shape(self) -> tuple[int, ...]:
        """``(X, Y, Z)``, or ``(X, Y)`` for BEV."""
        return self.grid.shape[:2] if self.bev else self.grid.shape

    @property
    def num_cells(self) -> int:
        """``V``: cells of one output volume."""
        return math.prod(self.out_shape)

    def cell_index(self, batch: Any, h: int, w: int, depths: Tensor) -> Tensor:
        """``(B, N, D, h, w)`` int64 flat output cell in ``[0, V)`` of every frustum point (per sample), -1: dropped.

        The flat cell is ``(i*Y + j)*Z + k`` (3D) or ``i*Y + j`` (BEV), the layout of :attr:`out_shape`.
        """
        with _no_autocast(depths.device):
            points = frustum_points(batch, h, w, self.image_stride, depths, dtype=torch.float64)
            hook = self._point_to_index or self.grid.coord_to_index
            idx = hook(points)
            _, y, z = self.grid.shape
            inside = self.grid.index_in_bounds(idx)
            flat = idx[..., 0] * y + idx[..., 1]
            if not self.bev:
                flat = flat * z + idx[..., 2]
            return torch.where(inside, flat, torch.full_like(flat, -1))

    def geometry_keys(self, batch: Any, h: int, w: int, depths: Tensor) -> list[str]:
        """One exact fingerprint (:func:`geometry_key`) per batch item of everything its plan depends on.

        That is the item's ``intrinsics``, ``cam_to_ego``, ``img_aug`` and depth centres (as the
        float32 they are used in), the feature-map size, the stride, the grid, BEV or not and the device.
        Checks that the depth centres are positive and increasing.
        """
        b, n = batch.cam_to_ego.shape[:2]
        z = _depths_per_camera(depths.detach(), b, n).cpu()
        if not bool((z > 0).all()) or not bool((z.diff(dim=-1) > 0).all()):
            raise ValueError("depth centres must be positive and strictly increasing along D")
        parts = [t.detach().float().reshape(b, -1).cpu() for t in (batch.intrinsics, batch.cam_to_ego, batch.img_aug)]
        geometry = torch.cat([*parts, z.reshape(b, -1)], dim=1)
        shapes = tuple(tuple(t.shape[1:]) for t in (batch.intrinsics, batch.cam_to_ego, batch.img_aug, z))
        static = {
            "h": int(h),
            "w": int(w),
            "stride": self.image_stride,
            "grid": self.grid,
            "bev": self.bev,
            "shapes": shapes,
            "device": str(depths.device),
        }
        return [geometry_key(geometry[i], **static) for i in range(b)]

    def plans(self, batch: Any, h: int, w: int, depths: Tensor) -> list[SplatPlan]:
        """The :class:`SplatPlan` of every batch item, from :attr:`plan_cache` or built.

        On a miss the cell index of the whole batch is computed once (:meth:`cell_index`, the
        same code the reference path runs) and a plan is built for each missing item.
        """
        keys = self.geometry_keys(batch, h, w, depths)
        plans: list[SplatPlan | None] = [self.plan_cache.get(k) for k in keys]
        if any(p is None for p in plans):
            index = self.cell_index(batch, h, w, depths)
            built: dict[str, SplatPlan] = {}
            for i, key in enumerate(keys):
                if plans[i] is not None:
                    continue
                if key not in built:
                    built[key] = build_splat_plan(index[i], self.num_cells)
                    self.plan_cache.put(key, built[key])
                plans[i] = built[key]
        return plans  # type: ignore[return-value]

    def _reference(self, rows: Tensor, batch: Any, h: int, w: int, depths: Tensor) -> Tensor:
        """Naive :func:`splat` of ``(B*N*D*h*w, C)`` channels-last point rows -> ``(B, C, *out_shape)``."""
        b = batch.cam_to_ego.shape[0]
        v, c = self.num_cells, rows.shape[1]
        index = self.cell_index(batch, h, w, depths)
        offset = torch.arange(b, device=index.device).view(b, 1, 1, 1, 1) * v
        flat = torch.where(index >= 0, index + offset, index).reshape(-1)
        volume = splat(rows, flat, b * v).view(b, *self.out_shape, c)
        return volume.movedim(-1, 1)

    def splat_outer(self, depth: Tensor, context: Tensor, batch: Any, depths: Tensor) -> Tensor:
        """Pool ``depth[b, n, d, r, c] * context[b, n, :, r, c]`` into the grid.

        Args:
            depth: ``(B, N, D, h, w)`` weights per frustum point (e.g. depth probabilities).
            context: ``(B, N, C, h, w)`` features per cell.
            batch: the calibration: ``intrinsics``, ``cam_to_ego``, ``img_aug`` (see :func:`frustum_points`).
            depths: depth centres ``(D,)``, ``(N, D)`` or ``(B, N, D)``, metres of camera-frame z.

        Returns:
            ``(B, C, *out_shape)``, contiguous; differentiable in ``depth`` and ``context``.
        """
        if depth.dim() != 5 or context.dim() != 5:
            raise ValueError(
                f"splat_outer: expected depth (B, N, D, h, w) and context (B, N, C, h, w), got "
                f"{tuple(depth.shape)} and {tuple(context.shape)}"
            )
        b, n, d, h, w = depth.shape
        c = context.shape[2]
        with _no_autocast(depth.device):
            depth, context = _pool_dtype(depth), _pool_dtype(context)
            if self.mode == "reference":
                # Outer product, channels last: (B, N, D, h, w, C), row order matching cell_index.
                frustum = depth.view(b, n, d, 1, h, w) * context.view(b, n, 1, c, h, w)
                rows = frustum.permute(0, 1, 2, 4, 5, 3).reshape(-1, c)
                return self._reference(rows, batch, h, w, depths).contiguous()
            plans = self.plans(batch, h, w, depths)
            return splat_outer(depth, context, plans).view(b, c, *self.out_shape)

    def splat_points(self, features: Tensor, batch: Any, depths: Tensor) -> Tensor:
        """Pool arbitrary per-point features ``features[b, n, d, :, r, c]`` into the grid.

        Args:
            features: ``(B, N, D, C, h, w)`` (a channels-last ``(B, N, D, h, w, C)`` tensor
                permuted to this shape costs no copy in the reference path).
            batch, depths: as in :meth:`splat_outer`.

        Returns:
            ``(B, C, *out_shape)``, contiguous; differentiable in ``features``.
        """
        if features.dim() != 6:
            raise ValueError(f"splat_points: expected features (B, N, D, C, h, w), got shape {tuple(features.shape)}")
        b, _, _, c, h, w = features.shape
        with _no_autocast(features.device):
            features = _pool_dtype(features)
            if self.mode == "reference":
                rows = features.permute(0, 1, 2, 4, 5, 3).reshape(-1, c)
                return self._reference(rows, batch, h, w, depths).contiguous()
            plans = self.plans(batch, h, w, depths)
            return splat_points(features, plans).view(b, c, *self.out_shape)
