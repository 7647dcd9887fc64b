"""DuOcc's dynamic query aggregation (DQA, paper §3.2 Eqs. 7-10, suppl. A.2) and its box geometry.

Selected instance queries are written into the voxels their 3D boxes cover. For voxel ``i`` with the
set ``N^i`` of selected queries whose boxes contain it (Eqs. 7-10)::

    q^i = W_Q (V^i + sigma_p^i)            k^ij = W_K q_vox^j     v^ij = W_V q_vox^j
    alpha^i = softmax_j(q^i . k^ij / sqrt(d))      z^i = sum_j alpha^ij v^ij
    g^i = sigmoid(W_gate [V^i, z^i])
    V_DQA^i = V^i + g^i * z^i   if N^i is not empty,   V^i otherwise (bit for bit).

Attention runs per head (``heads=1`` is the equation as printed); in eager its softmax runs over the edges
of each voxel only (an edge list, no dense voxel-by-query matrix); a traced graph (export, ``torch.compile``)
runs the same equations on a dense voxel-by-query mask (:meth:`DynamicQueryAggregation.dense`). The
feed-forward step that turns ``V_DQA`` into ``V_fin`` (§3.2, last paragraph) is :class:`VoxelFFN`, applied over
the whole grid.

Boxes are ``(..., 7)`` ``[cx, cy, cz, l, w, h, yaw]`` in the ego frame (extra columns, e.g. velocity,
are ignored): centre, length along the heading, width, height (metres), yaw about +z from +x (radians).

Paper versus the public code (``projects/mmdet3d_plugin/models/heads/queryagg/dqa.py``):

* coverage: a voxel belongs to a box when its centre lies inside the rotated box (``coverage="center"``,
  exact); the code takes the axis-aligned index range of the rounded box corners (``coverage="aabb"``),
  which over-covers rotated boxes;
* the code adds a LayerNorm on the instance features, an output projection and attention dropout, and
  runs its FFN's bias and norms over every voxel; here Eq. 10 holds exactly (no output projection) unless
  ``instance_norm`` / ``output_bias`` ask for the code's; its other habits are switches too (``outside_boxes``,
  ``empty_selection``, ``box_rotation``, ``positional_order``; ``duocc/code_recipe`` sets them all);
* selection (:func:`select_queries`): the paper's thresholds (IoU 0.4 for large objects, the geometric
  cost ``2 D_center + 1 D_size < 1.5`` for small ones) and the code's (no size split: cost
  ``0.5 D_center + 0.125 D_size < 1.5`` or IoU > 0.3) are both arguments (:data:`PAPER_SELECTION`,
  :data:`CODE_SELECTION`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Annotated, Literal

import torch
from torch import Tensor, nn

from occplug.constraints import Positive, check_choices
from occplug.geometry import GridSpec

__all__ = [
    "CODE_SELECTION",
    "PAPER_SELECTION",
    "DynamicQueryAggregation",
    "VoxelFFN",
    "box_iou_3d",
    "points_in_boxes",
    "select_queries",
]

#: DuOcc suppl. A.2's selection thresholds (small objects must be named: ``small_classes`` / ``small_size``).
PAPER_SELECTION = {
    "score_threshold": 0.3,
    "iou_threshold": 0.4,
    "cost_threshold": 1.5,
    "center_weight": 2.0,
    "size_weight": 1.0,
}
#: The public code's selection (no small/large split: cost or IoU); its cost is 0.25 x the matching
#: regression weights, i.e. ``0.5 * L1(centre) + 0.125 * L1(log size)``.
CODE_SELECTION = {
    "score_threshold": 0.3,
    "iou_threshold": 0.3,
    "cost_threshold": 1.5,
    "center_weight": 0.5,
    "size_weight": 0.125,
    "small_classes": None,
    "small_size": None,
}


# ---------------------------------------------------------------------------------------------- box geometry


def _inside(points: Tensor, boxes: Tensor) -> Tensor:
    """Elementwise (broadcast) test: ``(..., 3)`` points inside ``(..., >=7)`` closed rotated boxes -> ``(...)``."""
    d = points - boxes[..., :3]
    c, s = torch.cos(boxes[..., 6]), torch.sin(boxes[..., 6])
    along = d[..., 0] * c + d[..., 1] * s  # the point in the box's own frame (rotate by -yaw)
    across = -d[..., 0] * s + d[..., 1] * c
    return (
        (along.abs() <= boxes[..., 3] / 2)
        & (across.abs() <= boxes[..., 4] / 2)
        & (d[..., 2].abs() <= boxes[..., 5] / 2)
    )


def points_in_boxes(points: Tensor, boxes: Tensor) -> Tensor:
    """Which points lie inside which rotated 3D boxes (closed boxes: the faces count as inside).

    Args:
        points: ``(..., P, 3)`` ego-frame points, metres.
        boxes: ``(..., M, >=7)`` ``[cx, cy, cz, l, w, h, yaw]`` in the same frame; same leading dims.

    Returns:
        ``(..., P, M)`` bool.
    """
    return _inside(points[..., :, None, :], boxes[..., None, :, :])


def _cross(a: Tensor, b: Tensor) -> Tensor:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _bev_corners(boxes: Tensor) -> Tensor:
    """``(..., >=7)`` boxes -> ``(..., 4, 2)`` footprint corners, counter-clockwise."""
    sign = boxes.new_tensor([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]])
    local = sign * torch.stack([boxes[..., 3], boxes[..., 4]], -1)[..., None, :] / 2  # (..., 4, 2)
    c, s = torch.cos(boxes[..., 6])[..., None], torch.sin(boxes[..., 6])[..., None]
    x = local[..., 0] * c - local[..., 1] * s + boxes[..., None, 0]
    y = local[..., 0] * s + local[..., 1] * c + boxes[..., None, 1]
    return torch.stack([x, y], -1)


def _bev_overlap(a: Tensor, b: Tensor, tol: float = 1e-9) -> Tensor:
    """Intersection area of the footprints of broadcast ``(..., >=7)`` boxes -> ``(...)``.

    The overlap of two rectangles is convex: its vertices are the corners of each inside the other and
    the crossings of their edges (at most 24 candidates). The candidates are ordered by angle about
    their mean and the shoelace formula gives the area; duplicates add nothing.
    """
    a, b = torch.broadcast_tensors(a, b)
    ca, cb = _bev_corners(a), _bev_corners(b)
    a_in_b = _inside_footprint(ca, b[..., None, :], tol)
    b_in_a = _inside_footprint(cb, a[..., None, :], tol)
    ra, rb = ca.roll(-1, dims=-2) - ca, cb.roll(-1, dims=-2) - cb  # edge vectors
    p, r = ca[..., :, None, :], ra[..., :, None, :]
    q, s = cb[..., None, :, :], rb[..., None, :, :]
    den = _cross(r, s)  # (..., 4, 4)
    ok = den.abs() > tol
    den = torch.where(ok, den, torch.ones_like(den))
    t, u = _cross(q - p, s) / den, _cross(q - p, r) / den
    ok = ok & (t >= -tol) & (t <= 1 + tol) & (u >= -tol) & (u <= 1 + tol)
    crossings = p + t[..., None] * r
    pts = torch.cat([ca, cb, crossings.flatten(-3, -2)], -2)  # (..., 24, 2)
    valid = torch.cat([a_in_b, b_in_a, ok.flatten(-2)], -1)  # (..., 24)
    count = valid.sum(-1, keepdim=True)
    w = valid.to(pts.dtype)[..., None]
    centre = (pts * w).sum(-2) / count.clamp(min=1).to(pts.dtype)
    rel = pts - centre[..., None, :]
    angle = torch.where(valid, torch.atan2(rel[..., 1], rel[..., 0]), torch.full_like(rel[..., 0], 10.0))
    order = angle.argsort(-1)
    pts = pts.gather(-2, order[..., None].expand_as(pts))
    valid = valid.gather(-1, order)
    pts = torch.where(valid[..., None], pts, pts[..., :1, :])  # padding repeats the first vertex: zero area
    area = _cross(pts, pts.roll(-1, dims=-2)).sum(-1).abs() / 2
    return torch.where(count.squeeze(-1) >= 3, area, torch.zeros_like(area))


def _inside_footprint(points: Tensor, boxes: Tensor, tol: float) -> Tensor:
    """``(..., 2)`` points inside the ``(..., >=7)`` boxes' footprints, with a tolerance of ``tol`` metres."""
    d = points - boxes[..., :2]
    c, s = torch.cos(boxes[..., 6]), torch.sin(boxes[..., 6])
    along = d[..., 0] * c + d[..., 1] * s
    across = -d[..., 0] * s + d[..., 1] * c
    return (along.abs() <= boxes[..., 3] / 2 + tol) & (across.abs() <= boxes[..., 4] / 2 + tol)


def box_iou_3d(boxes_a: Tensor, boxes_b: Tensor) -> Tensor:
    """3D IoU of rotated boxes (yaw about z): footprint overlap times height overlap over the union volume.

    Exact up to float64 round-off (a plain-PyTorch stand-in for mmcv's ``boxes_iou3d``).

    Args:
        boxes_a: ``(N, >=7)`` ``[cx, cy, cz, l, w, h, yaw]``, ``cz`` the centre height.
        boxes_b: ``(M, >=7)``.

    Returns:
        ``(N, M)`` IoU in ``[0, 1]``, dtype of ``boxes_a``.
    """
    a = boxes_a[:, None, :7].to(torch.float64)
    b = boxes_b[None, :, :7].to(torch.float64)
    area = _bev_overlap(a, b)  # (N, M)
    top = torch.minimum(a[..., 2] + a[..., 5] / 2, b[..., 2] + b[..., 5] / 2)
    bottom = torch.maximum(a[..., 2] - a[..., 5] / 2, b[..., 2] - b[..., 5] / 2)
    inter = area * (top - bottom).clamp(min=0)
    vol_a = a[..., 3] * a[..., 4] * a[..., 5]
    vol_b = b[..., 3] * b[..., 4] * b[..., 5]
    iou = inter / (vol_a + vol_b - inter).clamp(min=1e-12)
    return iou.clamp(0, 1).to(boxes_a.dtype)


# ---------------------------------------------------------------------------------------------- selection


def select_queries(
    scores: Tensor,
    boxes: Tensor,
    classes: Tensor | None = None,
    score_threshold: float = 0.3,
    gt_boxes: Sequence[Tensor] | None = None,
    iou_threshold: float | None = 0.4,
    cost_threshold: float | None = 1.5,
    center_weight: float = 2.0,
    size_weight: float = 1.0,
    small_classes: Sequence[int] | None = None,
    small_size: float | None = None,
    max_queries: int | None = None,
) -> Tensor:
    """Which instance queries DQA writes into the voxels (suppl. A.2).

    Inference (``gt_boxes=None``): ``score > score_threshold``. Training: also a ground-truth check,
    against the best ground truth of the sample:

    * ``IoU > iou_threshold`` (3D IoU, :func:`box_iou_3d`), or
    * the geometric cost ``center_weight * D_center + size_weight * D_size < cost_threshold``, with
      ``D_center = sum |delta xyz|`` and ``D_size = sum |delta log(l, w, h)|`` (L1, as DuOcc's matching cost).

    With a small-object rule (``small_classes`` and/or ``small_size``), small queries take the cost test
    and the others the IoU test (the paper); without one, either test admits a query (the public code).
    A sample without ground truth selects nothing in training. ``None`` disables a test.

    Args:
        scores: ``(B, Q)`` confidence (the largest class sigmoid).
        boxes: ``(B, Q, >=7)`` predicted boxes, ego frame.
        classes: ``(B, Q)`` int64 predicted class ids (needed with ``small_classes``).
        score_threshold: both rules: 0.3.
        gt_boxes: ``B`` tensors ``(G_b, >=7)`` ground-truth boxes (training), or None (inference).
        iou_threshold: paper 0.4 (large objects), code 0.3.
        cost_threshold: 1.5 in both.
        center_weight, size_weight: paper 2.0 / 1.0, code 0.5 / 0.125.
        small_classes: class ids that count as small objects (the paper names none).
        small_size: a query whose largest box edge is below this (metres) counts as small.
        max_queries: keep at most this many per sample, highest scores first.

    Returns:
        ``(B, Q)`` bool.
    """
    selected = scores > score_threshold
    if gt_boxes is not None:
        if len(gt_boxes) != scores.shape[0]:
            raise ValueError(f"select_queries: {len(gt_boxes)} ground-truth sets for {scores.shape[0]} samples")
        split = small_classes is not None or small_size is not None
        small = torch.zeros_like(selected)
        if small_classes is not None:
            if classes is None:
                raise ValueError("select_queries: small_classes needs the predicted classes")
            small = small | torch.isin(classes, torch.as_tensor(list(small_classes), device=classes.device))
        if small_size is not None:
            small = small | (boxes[..., 3:6].amax(-1) < small_size)
        passed = []
        for b, gt in enumerate(gt_boxes):
            pred = boxes[b, :, :7].detach()
            if gt.shape[0] == 0:
                passed.append(torch.zeros_like(selected[b]))
                continue
            gt = gt[:, :7].to(pred)
            no = torch.zeros_like(selected[b])
            iou_ok = no if iou_threshold is None else box_iou_3d(pred, gt).amax(1) > iou_threshold
            if cost_threshold is None:
                cost_ok = no
            else:
                d_center = (pred[:, None, :3] - gt[None, :, :3]).abs().sum(-1)
                d_size = (pred[:, None, 3:6].log() - gt[None, :, 3:6].log()).abs().sum(-1)
                cost_ok = (center_weight * d_center + size_weight * d_size).amin(1) < cost_threshold
            passed.append(torch.where(small[b], cost_ok, iou_ok) if split else iou_ok | cost_ok)
        selected = selected & torch.stack(passed)
    if max_queries is not None and max_queries < scores.shape[1]:
        ranked = torch.where(selected, scores, torch.full_like(scores, -math.inf))
        top = ranked.topk(max_queries, dim=1).indices
        keep = torch.zeros_like(selected).scatter(1, top, True)
        selected = selected & keep
    return selected


# ---------------------------------------------------------------------------------------------- aggregation


class DynamicQueryAggregation(nn.Module):
    """Query-to-voxel attention with a gate, written only into the voxels of the selected boxes (Eqs. 7-10).

    Args:
        channels: ``C`` of the voxel features (divisible by ``heads``).
        grid: the (metric) grid the volume lies on, ego frame (``GridSpec`` or ``{range, voxel_size}``).
        query_channels: width of the instance queries (default ``C``).
        heads: attention heads (``heads=1``: Eq. 8 as printed; the code uses 8).
        coverage: ``"center"`` (voxel centre inside the rotated box) or ``"aabb"`` (the code's
            axis-aligned range of rounded corner indices).
        positional: add the learned positional encoding ``sigma_p`` to the voxel side (Eq. 7): one table
            per axis, ``3C/8 + 3C/8 + rest`` channels concatenated (the code's 96 + 96 + 64 of 256).
        output_bias: the public code's output projection ``W_O`` (with bias) on the message; its bias reaches
            every voxel, covered or not (off: Eq. 10, no projection, uncovered voxels unchanged).
        instance_norm: the public code's LayerNorm on the instance features before ``W_K`` / ``W_V``.
        outside_boxes: a box whose index range misses the grid writes nothing (``"skip"``), or, as the public
            code, its range is clamped onto the grid, a one-voxel slab on the nearest face (``"clamp"``; with
            ``coverage="center"`` the slab's centres are still tested, so it matters with ``"aabb"``).
        empty_selection: a sample with no selected query writes nothing (``"skip"``), or, as the public code,
            query 0's box is written with a zero feature (``"dummy_query"``); in that mode, as in the code, an
            edge whose (normalised) instance feature sums to exactly zero carries no value (it still takes its
            share of the softmax).
        box_rotation: ``"yaw"`` reads box column 6 as the yaw; ``"sin_cos"`` reads columns 6 and 7 as the
            detector's raw, unnormalised ``(sin, cos)`` (the public code's box corners); ``coverage="center"``
            then uses ``atan2(sin, cos)``.
        positional_order: channel blocks of ``sigma_p``: ``[x | y | z]`` tables (``"xyz"``) or the public
            code's ``[y | x | z]`` (``"yxz"``, its row embedding is the y axis); the parameters are the same.

    Forward: see :meth:`forward`.
    """

    def __init__(
        self,
        channels: Annotated[int, Positive],
        grid: GridSpec,
        query_channels: int | None = None,
        heads: Annotated[int, Positive] = 8,
        coverage: Literal["center", "aabb"] = "center",
        positional: bool = True,
        output_bias: bool = False,
        instance_norm: bool = False,
        outside_boxes: Literal["skip", "clamp"] = "skip",
        empty_selection: Literal["skip", "dummy_query"] = "skip",
        box_rotation: Literal["yaw", "sin_cos"] = "yaw",
        positional_order: Literal["xyz", "yxz"] = "xyz",
    ) -> None:
        super().__init__()
        if channels % heads:
            raise ValueError(f"DynamicQueryAggregation: channels {channels} not divisible by heads {heads}")
        check_choices(
            DynamicQueryAggregation.__init__,
            "DynamicQueryAggregation",
            coverage=coverage,
            outside_boxes=outside_boxes,
            empty_selection=empty_selection,
            box_rotation=box_rotation,
            positional_order=positional_order,
        )
        self.outside_boxes, self.empty_selection = outside_boxes, empty_selection
        self.box_rotation, self.positional_order = box_rotation, positional_order
        self.grid = grid
        if self.grid.is_contracted:
            raise ValueError("DynamicQueryAggregation needs a metric grid (boxes are found by voxel index)")
        self.channels, self.heads, self.coverage = int(channels), int(heads), coverage
        qc = int(query_channels or channels)
        self.w_q = nn.Linear(channels, channels)
        self.w_k = nn.Linear(qc, channels)
        self.w_v = nn.Linear(qc, channels)
        self.w_gate = nn.Linear(2 * channels, channels)
        self.w_out = nn.Linear(channels, channels) if output_bias else None
        self.instance_norm = nn.LayerNorm(qc) if instance_norm else None
        self.pos = None
        if positional:
            cx = cy = 3 * channels // 8
            sizes = (cx, cy, channels - cx - cy)
            self.pos = nn.ParameterList(
                nn.Parameter(torch.rand(n, c)) for n, c in zip(self.grid.shape, sizes, strict=True)
            )

    def _metric(self, device: torch.device) -> tuple[Tensor, Tensor]:
        """``(lower, voxel_size)`` of the grid, ``(3,)`` float64 metres each."""
        lower = torch.tensor(self.grid.lower, dtype=torch.float64, device=device)
        return lower, torch.tensor(self.grid.voxel_size, dtype=torch.float64, device=device)

    def _index_range(self, bx: Tensor) -> tuple[Tensor, Tensor]:
        """``(..., 7)`` float64 boxes -> ``(lo, hi)`` ``(..., 3)`` int64: the voxel index range (inclusive, unclipped)
        of each box's axis-aligned extent (``"center"``: floored; ``"aabb"``: the code's rounded corners)."""
        lower, size = self._metric(bx.device)
        if self.box_rotation == "sin_cos":  # raw (sin, cos): an unnormalised pair scales the corners, as in the code
            c, s = bx[..., 7].abs(), bx[..., 6].abs()
        else:
            c, s = torch.cos(bx[..., 6]).abs(), torch.sin(bx[..., 6]).abs()
        half = torch.stack([bx[..., 3] * c + bx[..., 4] * s, bx[..., 3] * s + bx[..., 4] * c, bx[..., 5]], -1) / 2
        lo, hi = (bx[..., :3] - half - lower) / size, (bx[..., :3] + half - lower) / size  # in voxel units
        if self.coverage == "aabb":  # the code: round the corners' positions, keep the whole index range
            lo, hi = torch.round(lo).long(), torch.round(hi).long()
        else:
            lo, hi = torch.floor(lo).long(), torch.floor(hi).long()
        if self.outside_boxes == "clamp":  # the code clamps each end onto the grid: an outside box keeps a face slab
            top = torch.tensor(self.grid.shape, device=bx.device) - 1
            lo, hi = lo.clamp(min=0).minimum(top), hi.clamp(min=0).minimum(top)
        return lo, hi

    def _yaw_boxes(self, bx: Tensor) -> Tensor:
        """``(..., >=7)`` float64 boxes -> ``(..., 7)`` with column 6 the yaw (``atan2`` of a raw ``(sin, cos)``)."""
        if self.box_rotation == "sin_cos":
            return torch.cat([bx[..., :6], torch.atan2(bx[..., 6], bx[..., 7])[..., None]], -1)
        return bx[..., :7]

    def edges(self, boxes: Tensor) -> tuple[Tensor, Tensor]:
        """The (voxel, query) pairs of one sample's boxes: voxel ``i`` of the flat ``X*Y*Z`` grid lies in box ``j``.

        Only the voxels of each box's axis-aligned index range are tested (no voxel-by-box matrix).

        Args:
            boxes: ``(Q, >=7)`` boxes, ego frame.

        Returns:
            ``(voxel_idx (E,), query_idx (E,))`` int64, ordered by query then voxel.
        """
        device = boxes.device
        shape = torch.tensor(self.grid.shape, device=device)
        lower, size = self._metric(device)
        bx = boxes[:, : 8 if self.box_rotation == "sin_cos" else 7].to(torch.float64)
        lo, hi = self._index_range(bx)
        hits_grid = ((hi >= 0) & (lo < shape)).all(-1)
        lo, hi = torch.maximum(lo, torch.zeros_like(lo)), torch.minimum(hi, shape - 1)
        extent = torch.where(hits_grid[:, None], hi - lo + 1, torch.zeros_like(lo))  # (Q, 3)
        if boxes.shape[0] == 0 or int(extent.prod(-1).max()) == 0:
            empty = torch.zeros(0, dtype=torch.int64, device=device)
            return empty, empty.clone()
        span = extent.amax(0).tolist()
        offsets = torch.stack(torch.meshgrid(*(torch.arange(n, device=device) for n in span), indexing="ij"), -1).view(
            -1, 3
        )
        index = lo[:, None, :] + offsets[None]  # (Q, E, 3) candidate voxels of each box
        keep = (offsets[None] < extent[:, None, :]).all(-1)
        if self.coverage == "center":
            centers = lower + (index.to(torch.float64) + 0.5) * size
            keep = keep & _inside(centers, self._yaw_boxes(bx)[:, None, :])
        query_idx, cand = keep.nonzero(as_tuple=True)
        ijk = index[query_idx, cand]
        voxel_idx = (ijk[:, 0] * shape[1] + ijk[:, 1]) * shape[2] + ijk[:, 2]
        return voxel_idx, query_idx

    def membership(self, boxes: Tensor, selected: Tensor) -> Tensor:
        """Dense form of :meth:`edges` for a batch: voxel ``i`` of the flat ``X*Y*Z`` grid lies in selected box ``j``.

        The same coverage rule as :meth:`edges`, tested for every voxel and box (no data-dependent shapes).

        Args:
            boxes: ``(B, Q, >=7)`` boxes, ego frame.
            selected: ``(B, Q)`` bool.

        Returns:
            ``(B, N, Q)`` bool, ``N = X * Y * Z``.
        """
        ijk = torch.stack(
            torch.meshgrid(*(torch.arange(n, device=boxes.device) for n in self.grid.shape), indexing="ij"), -1
        ).view(-1, 3)  # (N, 3), flat order
        bx = boxes[..., : 8 if self.box_rotation == "sin_cos" else 7].to(torch.float64)
        if self.coverage == "center":
            lower, size = self._metric(boxes.device)
            centers = lower + (ijk.to(torch.float64) + 0.5) * size
            # (a clamped slab lies outside its box: the centre test alone is edges()' result)
            inside = _inside(centers[None, :, None, :], self._yaw_boxes(bx)[:, None, :, :])
        else:  # every voxel of the box's index range, as in edges()
            lo, hi = self._index_range(bx)
            at = ijk[None, :, None, :]
            inside = ((at >= lo[:, None]) & (at <= hi[:, None])).all(-1)
        return inside & selected[:, None, :]

    def forward(self, volume: Tensor, queries: Tensor, boxes: Tensor, selected: Tensor) -> Tensor:
        """Write the selected queries into the voxels of their boxes.

        Eager runs on the edge list (:meth:`edges`, a scatter softmax per voxel); a traced graph (``torch.export``,
        ``torch.compile``) cannot hold its data-dependent sizes and runs :meth:`dense`, the same equations over
        every voxel and query with a mask: tensors of ``B * N * Q * heads`` floats, a few alive at once (nothing on the
        synthetic grids; 2.3 GB each in float32 per sample at the paper's 100 x 100 x 8 voxels, 900 queries, 8 heads).

        Args:
            volume: ``V_S.A``, ``(B, C, X, Y, Z)`` on the grid, ego frame.
            queries: ``q_vox``, ``(B, Q, C_q)`` instance features.
            boxes: ``(B, Q, >=7)`` their boxes ``[cx, cy, cz, l, w, h, yaw]``, ego frame.
            selected: ``(B, Q)`` bool (:func:`select_queries`).

        Returns:
            ``V_DQA``, ``(B, C, X, Y, Z)``: equal to ``volume`` bit for bit at every voxel no selected box covers.
        """
        if tuple(volume.shape[2:]) != self.grid.shape:
            raise ValueError(f"DynamicQueryAggregation: volume {tuple(volume.shape)} is not on grid {self.grid.shape}")
        if torch.compiler.is_compiling():
            return self.dense(volume, queries, boxes, selected)
        return self.sparse(volume, queries, boxes, selected)

    def _positional(self, flat_idx: Tensor) -> Tensor:
        """``sigma_p`` of flat voxel indices ``(N,)`` -> ``(N, C)``."""
        assert self.pos is not None
        ny, nz = self.grid.shape[1:]
        ijk = (flat_idx // (ny * nz), (flat_idx // nz) % ny, flat_idx % nz)
        blocks = [table[k] for table, k in zip(self.pos, ijk, strict=True)]
        if self.positional_order == "yxz":
            blocks = [blocks[1], blocks[0], blocks[2]]
        return torch.cat(blocks, -1)

    def _dummy(self, queries: Tensor, selected: Tensor) -> tuple[Tensor, Tensor]:
        """``empty_selection="dummy_query"``: a sample with nothing selected selects query 0 with a zero feature."""
        empty = ~selected.any(1, keepdim=True)  # (B, 1)
        first = torch.arange(selected.shape[1], device=selected.device)[None] == 0
        dummy = empty & first  # (B, Q)
        return queries.masked_fill(dummy[..., None], 0.0), selected | dummy

    def _keys(self, feats: Tensor) -> tuple[Tensor, Tensor]:
        """``(..., C_q)`` instance features -> keys and values ``(..., C)`` (values zero where the code masks them)."""
        if self.instance_norm is not None:
            feats = self.instance_norm(feats)
        k, v = self.w_k(feats), self.w_v(feats)
        if self.empty_selection == "dummy_query":  # the code's mask: a feature summing to exactly 0 sends no value
            v = v * (feats.sum(-1, keepdim=True) != 0).to(v.dtype)
        return k, v

    def dense(self, volume: Tensor, queries: Tensor, boxes: Tensor, selected: Tensor) -> Tensor:
        """:meth:`forward` with a ``(B, N, Q)`` mask in place of the edge list: fixed shapes, so it traces.

        Same arguments and result as :meth:`forward` (``N = X * Y * Z`` voxels in flat order). The logits are
        ``(B, N, Q, heads)``; the softmax runs over the queries covering each voxel; a voxel no selected box covers
        keeps ``volume`` bit for bit (``torch.where``), as on the edge list.
        """
        b, c = volume.shape[:2]
        h, d = self.heads, c // self.heads
        flat = volume.reshape(b, c, -1).transpose(1, 2)  # (B, N, C)
        if self.empty_selection == "dummy_query":
            queries, selected = self._dummy(queries, selected)
        member = self.membership(boxes, selected)  # (B, N, Q)
        qin = flat
        if self.pos is not None:
            qin = flat + self._positional(torch.arange(flat.shape[1], device=flat.device)).to(flat)
        q = self.w_q(qin).view(b, -1, h, d)
        # an unselected query's weight is 0, but 0 * inf is NaN: keep its (possibly non-finite) features out
        queries = queries.masked_fill(~selected[..., None], 0.0)
        k, v = self._keys(queries)
        k, v = k.view(b, -1, h, d), v.view(b, -1, h, d)
        logits = torch.einsum("bnhd,bqhd->bnqh", q, k) / math.sqrt(d)
        logits = logits.masked_fill(~member[..., None], -math.inf)
        covered = member.any(-1)  # (B, N)
        # an uncovered voxel's row is all -inf: give it zeros (its result is discarded below) so no NaN appears
        alpha = torch.softmax(torch.where(covered[..., None, None], logits, torch.zeros_like(logits)), dim=2)
        z = torch.einsum("bnqh,bqhd->bnhd", alpha, v).reshape(b, -1, c)
        gate = torch.sigmoid(self.w_gate(torch.cat([flat, z], -1)))
        if self.w_out is not None:  # the code: W_O over every voxel's message (zero where uncovered: its bias)
            updated = flat + self.w_out(torch.where(covered[..., None], gate * z, torch.zeros_like(z)))
        else:
            updated = torch.where(covered[..., None], flat + gate * z, flat)
        return updated.transpose(1, 2).reshape(volume.shape)

    def sparse(self, volume: Tensor, queries: Tensor, boxes: Tensor, selected: Tensor) -> Tensor:
        """:meth:`forward` on the edge list of each sample (only the covered voxels are computed)."""
        b, c = volume.shape[:2]
        h, d = self.heads, c // self.heads
        out = []
        if self.empty_selection == "dummy_query":
            queries, selected = self._dummy(queries, selected)
        for i in range(b):
            flat = volume[i].reshape(c, -1)  # (C, N)
            base = flat  # what an uncovered voxel ends as
            if self.w_out is not None:  # W_O's bias reaches every voxel (the message is zero where uncovered)
                base = flat + self.w_out.bias.to(flat)[:, None]
            sel = selected[i].nonzero(as_tuple=True)[0]
            voxel_idx, edge_q = self.edges(boxes[i, sel])
            if voxel_idx.numel() == 0:
                out.append(base.view_as(volume[i]))
                continue
            covered, edge_v = torch.unique(voxel_idx, return_inverse=True)  # (Nc,), (E,)
            v_cov = flat[:, covered].t()  # (Nc, C)
            qin = v_cov
            if self.pos is not None:
                qin = v_cov + self._positional(covered).to(v_cov)
            q = self.w_q(qin).view(-1, h, d)
            k, v = self._keys(queries[i, sel])
            k, v = k.view(-1, h, d)[edge_q], v.view(-1, h, d)[edge_q]  # (E, h, d)
            logits = (q[edge_v] * k).sum(-1) / math.sqrt(d)  # (E, h)
            # softmax over the edges of each voxel (a scatter softmax; the shift only steadies exp)
            top = torch.full((covered.numel(), h), -math.inf, dtype=logits.dtype, device=logits.device)
            top = top.scatter_reduce(0, edge_v[:, None].expand(-1, h), logits.detach(), "amax")
            e = (logits - top[edge_v]).exp()
            total = torch.zeros_like(top).index_add(0, edge_v, e)
            alpha = e / total[edge_v]
            z = torch.zeros(covered.numel(), h, d, dtype=v.dtype, device=v.device)
            z = z.index_add(0, edge_v, alpha[..., None] * v).reshape(-1, c)  # (Nc, C)
            gate = torch.sigmoid(self.w_gate(torch.cat([v_cov, z], -1)))
            updated = v_cov + (gate * z if self.w_out is None else self.w_out(gate * z))
            out.append(base.index_copy(1, covered, updated.t().to(flat.dtype)).view_as(volume[i]))
        return torch.stack(out)


class VoxelFFN(nn.Module):
    """``V_fin = LN(V + MLP(LN(V)))`` per voxel: the feed-forward step after DQA (§3.2; code: hidden ``4C``).

    Args:
        channels: ``C``; hidden: MLP width (default ``4C``); final_norm: the closing LayerNorm (code: on).

    Forward: ``(B, C, X, Y, Z)`` -> ``(B, C, X, Y, Z)``.
    """

    def __init__(self, channels: Annotated[int, Positive], hidden: int | None = None, final_norm: bool = True) -> None:
        super().__init__()
        hidden = int(hidden or 4 * channels)
        self.norm = nn.LayerNorm(channels)
        self.mlp = nn.Sequential(nn.Linear(channels, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, channels))
        self.final = nn.LayerNorm(channels) if final_norm else nn.Identity()

    def forward(self, volume: Tensor) -> Tensor:
        x = volume.movedim(1, -1)
        x = self.final(x + self.mlp(self.norm(x)))
        return x.movedim(-1, 1)
