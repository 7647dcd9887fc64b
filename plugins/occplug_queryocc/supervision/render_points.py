"""QueryOcc's rendering-only supervision source ``queryocc_render_points`` (the paper's supervision ablation).

The same queryable field ``queryocc_query_points`` trains, supervised in image space instead of in 3D: from the
pixels with a pseudo depth (the current frame's cameras, or an adjacent frame's moved into the current ego
frame with the poses; the queries keep that frame's time ``t``), ``rays_per_sample`` rays per sample are
drawn, each sampled at ``samples_per_ray`` stratified camera depths ``d_1 < ... < d_S`` in ``[near, far]``
(``S`` equal bins, one uniform jitter per bin), and the head is queried at the points
``o + d_i / z_dir * dir`` (``z_dir``: the ray's camera-frame z per metre, so ``d_i`` is camera-frame z).
Alpha blending over its answers ``(o_i, s_i)``:

* ``alpha_i = sigmoid(o_i)``, ``T_i = prod_{j<i} (1 - alpha_j)``, ``w_i = T_i alpha_i``;
* depth ``D = sum_i w_i d_i + T_{S+1} far``: the leftover ``T_{S+1} = 1 - sum_i w_i`` (what passes every
  sample) is placed at ``far``, so an empty ray renders ``far``;
* semantics ``P(c) = sum_i w_i softmax(s_i)_c / sum_i w_i`` over the ``K - 1`` classes other than ``free``
  (computed in log space, so a nearly empty ray still gives a normalised distribution).

With ``sky_rays > 0``, that many further rays per sample go through pixels whose pseudo class is free (sky),
with ``d* = inf``: rendered free up to ``far``, the same information the query source gets.

Losses: ``L = l_depth |D - min(d*, far)| / min(d*, far) + l_sem (-log P(c*))`` with the pixel's pseudo depth ``d*`` (camera
z, as ``pseudo_depth`` stores it) and pseudo class ``c*``. A pixel deeper than ``far`` is a ray free up to
``far``: its depth target is ``far`` and it has no semantic term (nor does ``ignore_label``, nor ``free``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from occplug.constraints import Length, NonNegative, Positive, Range, check_choices
from occplug.data import Batch
from occplug.geometry import invert_pose, transform_points, unproject_from_image
from occplug.interfaces import ModelOutputs, SupervisionSource

from .query_points import QuerySupervision

__all__ = ["RaySet", "RenderSupervision", "Rendered", "render_rays", "sample_rays", "transmittance_weights"]


def transmittance_weights(occupancy_logit: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(alpha, T, w)`` of ``(..., S)`` occupancy logits ordered near to far: ``alpha_i = sigmoid(o_i)``,
    ``T_i = prod_{j<i} (1 - alpha_j)`` (``T_1 = 1``), ``w_i = T_i alpha_i``."""
    log_free = F.logsigmoid(-occupancy_logit)
    log_t = torch.cat([torch.zeros_like(log_free[..., :1]), log_free.cumsum(-1)[..., :-1]], -1)
    return torch.sigmoid(occupancy_logit), log_t.exp(), (log_t + F.logsigmoid(occupancy_logit)).exp()


@dataclass
class Rendered:
    """Rays rendered by :func:`render_rays`: ``depth`` ``(...)``, ``weights`` ``(..., S)``, ``leftover``
    ``(...)`` (``1 - sum w``, placed at ``far``), ``log_probs`` ``(..., K')`` log of the normalised rendered
    class distribution over the ``K' = K - 1`` classes other than ``free`` (in label order, ``free`` removed)."""

    depth: Tensor
    weights: Tensor
    leftover: Tensor
    log_probs: Tensor


def render_rays(
    occupancy_logit: Tensor, class_logits: Tensor, depths: Tensor, far: float, free_label: int | None
) -> Rendered:
    """Alpha-blend ``(..., S)`` occupancy logits and ``(..., S, K)`` class logits at ``(..., S)`` sample depths
    (near to far) into a depth and a class distribution (see the module docstring)."""
    log_free = F.logsigmoid(-occupancy_logit)
    log_t = torch.cat([torch.zeros_like(log_free[..., :1]), log_free.cumsum(-1)[..., :-1]], -1)
    log_w = log_t + F.logsigmoid(occupancy_logit)  # (..., S)
    weights = log_w.exp()
    leftover = log_free.sum(-1).exp()  # T after the last sample = 1 - sum w exactly (telescoping)
    depth = (weights * depths).sum(-1) + leftover * far
    k = class_logits.shape[-1]
    if free_label is not None and 0 <= free_label < k:
        keep = torch.tensor([c for c in range(k) if c != free_label], device=class_logits.device)
        class_logits = class_logits.index_select(-1, keep)
    log_p = class_logits.float().log_softmax(-1)  # (..., S, K')
    log_probs = torch.logsumexp(log_w.unsqueeze(-1) + log_p, -2) - torch.logsumexp(log_w, -1, keepdim=True)
    return Rendered(depth, weights, leftover, log_probs)


class RaySet:
    """Sampled rays of one batch: ``points`` ``(B, R, S, 3)`` (current ego frame), ``times`` ``(B, R)``,
    ``depths`` ``(B, R, S)`` camera-frame z of the samples, ``target_depth`` ``(B, R)`` the pixel's pseudo depth
    (camera z), ``labels`` ``(B, R)`` int64 its pseudo class, ``valid`` ``(B, R)`` bool (False: a placeholder
    ray of a sample without any pixel)."""

    def __init__(
        self, points: Tensor, times: Tensor, depths: Tensor, target_depth: Tensor, labels: Tensor, valid: Tensor
    ):
        self.points, self.times, self.depths = points, times, depths
        self.target_depth, self.labels, self.valid = target_depth, labels, valid

    @property
    def num_queries(self) -> int:
        """Head queries per sample: rays x samples per ray."""
        return int(self.points.shape[1] * self.points.shape[2])


def sample_rays(
    batch: Batch,
    offsets: list[int],
    rays_per_sample: int,
    samples_per_ray: int,
    near: float,
    far: float,
    ignore_label: int,
    pixel_stride: int = 1,
    max_depth: float = float("inf"),
    near_range: float | None = None,
    generator: torch.Generator | None = None,
    log_spacing: bool = True,
    sky_rays: int = 0,
    free_label: int | None = None,
) -> RaySet:
    """Draw ``rays_per_sample`` pixels per sample (with replacement, uniformly among every ``pixel_stride``-th
    pixel with a pseudo depth in ``(0, max_depth]`` of every camera of every frame offset in ``offsets``) and
    ``samples_per_ray`` stratified depths in ``[near, far]`` along each: one uniform draw in each of ``S`` bins
    of equal depth ratio (``log_spacing``, the default: dense near the camera where most surfaces are, as
    QueryOcc's log-linear bins) or of equal length.

    Args:
        offsets: frame offsets (0: the current frame; others must be in ``batch.adjacent``).
        near_range: keep only pixels whose pseudo point lies within this half-extent in x and y (metres,
            current ego frame); ``None``: all.
        sky_rays: further rays per sample drawn (the same way) among the pixels whose pseudo class is
            ``free_label`` (sky), whatever their depth: rays that end at no surface, with target depth ``inf``
            (rendered free up to ``far``) and label ``free_label``; they follow the ``rays_per_sample`` rays.
    """
    if sky_rays > 0 and free_label is None:
        raise ValueError("queryocc_render_points: sky_rays > 0 needs a free_label (the class sky pixels map to)")
    b, r, s = len(batch), rays_per_sample, samples_per_ray
    device = batch.images.device
    frames = []  # per frame offset: (offset, frame, strided rows, strided columns)
    for k in offsets:
        frame = batch if k == 0 else batch.adjacent.get(k)
        if frame is None:
            raise ValueError(
                f"queryocc_render_points: frame offset {k} is not loaded (set data.adjacent_offsets to include {k})"
            )
        if frame.pseudo_depth is None:
            raise ValueError("queryocc_render_points: the batch has no pseudo_depth (set data.pseudo_labels)")
        h, w = frame.pseudo_depth.shape[-2:]
        rows = torch.arange(0, h, pixel_stride, device=device)
        cols = torch.arange(0, w, pixel_stride, device=device)
        frames.append((k, frame, rows, cols))
    pts, tms, deps, tgts, labs, vals = [], [], [], [], [], []
    if log_spacing:  # bins of equal ratio (near -> far), one uniform sample in each: dense where surfaces are
        edges = near * (far / near) ** (torch.arange(s + 1, device=device, dtype=torch.float32) / s)
    else:
        edges = near + torch.arange(s + 1, device=device, dtype=torch.float32) * ((far - near) / s)
    for i in range(b):
        cands = []  # (frame slot, cam, row, col, depth)
        for slot, (k, frame, rows, cols) in enumerate(frames):
            z = frame.pseudo_depth[i][:, rows][:, :, cols].float()  # (N, h', w')
            keep = (z > 0) & (z <= max_depth) & (not _repeats_current(batch, frame, k, i))
            cam, ri, ci = torch.nonzero(keep, as_tuple=True)
            row, col, zz = rows[ri], cols[ci], z[cam, ri, ci]
            if near_range is not None and len(cam):
                ego = _to_current(batch, frame, k, i, _unproject(frame, i, cam, row, col, zz[:, None]))[:, 0]
                inside = (ego[:, :2].abs() <= near_range).all(-1)
                cam, row, col, zz = cam[inside], row[inside], col[inside], zz[inside]
            cands.append((torch.full_like(cam, slot), cam, row, col, zz))
        slot, cam, row, col, zz = (torch.cat(c) for c in zip(*cands, strict=True))
        n = len(cam)
        valid = torch.full((r,), n > 0, dtype=torch.bool, device=device)
        if n == 0:  # placeholder rays (camera 0, pixel (0, 0)) that the losses mask out
            slot = torch.zeros(1, dtype=torch.int64, device=device)
            cam, row, col = slot.clone(), slot.clone(), slot.clone()
            zz = torch.full((1,), near, device=device)
            n = 1
        pick = torch.randint(0, n, (r,), generator=generator).to(device)
        slot, cam, row, col, target = slot[pick], cam[pick], row[pick], col[pick], zz[pick]
        jitter = torch.rand(r, s, generator=generator).to(device)
        if sky_rays > 0:
            sky = _draw_sky(batch, frames, i, free_label, sky_rays, generator)
            slot, cam, row, col = (torch.cat([a, c]) for a, c in zip((slot, cam, row, col), sky[:4], strict=True))
            target = torch.cat([target, torch.full((sky_rays,), float("inf"), device=device)])
            jitter = torch.cat([jitter, torch.rand(sky_rays, s, generator=generator).to(device)])
            valid = torch.cat([valid, sky[4]])
        depths = edges[:-1] + jitter * (edges[1:] - edges[:-1])  # (R, S) stratified
        points = torch.empty(len(cam), s, 3, device=device)
        times = torch.zeros(len(cam), device=device)
        labels = torch.full((len(cam),), ignore_label, dtype=torch.int64, device=device)
        for f, (k, frame, _, _) in enumerate(frames):
            sel = slot == f
            if not bool(sel.any()):
                continue
            points[sel] = _to_current(
                batch, frame, k, i, _unproject(frame, i, cam[sel], row[sel], col[sel], depths[sel])
            )
            if k != 0:
                times[sel] = float(frame.timestamp[i] - batch.timestamp[i])
            if frame.pseudo_semantics is not None:
                labels[sel] = frame.pseudo_semantics[i][cam[sel], row[sel], col[sel]].long()
        pts.append(points)
        tms.append(times)
        deps.append(depths)
        tgts.append(target)
        labs.append(labels)
        vals.append(valid)
    return RaySet(
        torch.stack(pts), torch.stack(tms), torch.stack(deps), torch.stack(tgts), torch.stack(labs), torch.stack(vals)
    )


def _repeats_current(batch: Batch, frame: Batch, k: int, i: int) -> bool:
    """Whether adjacent frame ``frame`` (offset ``k``) of sample ``i`` is the current frame again: the data clamps
    an offset at the scene's ends (the same token), and such a frame is no other time, so it gives no rays."""
    return k != 0 and frame.token[i] == batch.token[i]


def _draw_sky(
    batch: Batch, frames: list, i: int, free_label: int, count: int, generator: torch.Generator | None
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """``count`` pixels of sample ``i`` drawn with replacement among the strided pixels of class ``free_label``
    of every frame slot: ``(slot, cam, row, col, valid)``, each ``(count,)`` (valid False: no such pixel)."""
    cands = []
    for slot, (k, frame, rows, cols) in enumerate(frames):
        if frame.pseudo_semantics is None:
            raise ValueError("queryocc_render_points: sky_rays needs pseudo_semantics (set data.pseudo_labels)")
        free = (frame.pseudo_semantics[i][:, rows][:, :, cols] == free_label) & (
            not _repeats_current(batch, frame, k, i)
        )
        cam, ri, ci = torch.nonzero(free, as_tuple=True)
        cands.append((torch.full_like(cam, slot), cam, rows[ri], cols[ci]))
    slot, cam, row, col = (torch.cat(c) for c in zip(*cands, strict=True))
    n = len(cam)
    valid = torch.full((count,), n > 0, dtype=torch.bool, device=cam.device)
    if n == 0:
        zero = torch.zeros(count, dtype=torch.int64, device=cam.device)
        return zero, zero, zero, zero, valid
    pick = torch.randint(0, n, (count,), generator=generator).to(cam.device)
    return slot[pick], cam[pick], row[pick], col[pick], valid


def _unproject(frame: Batch, i: int, cam: Tensor, row: Tensor, col: Tensor, depth: Tensor) -> Tensor:
    """``(R, S, 3)`` ego-frame points (of ``frame``) at ``(R, S)`` camera depths along the rays of the pixel
    centres ``(u, v) = (col, row)`` of cameras ``cam`` of sample ``i``."""
    uv = torch.stack([col, row], -1).to(torch.float32)[:, None].expand(-1, depth.shape[1], 2)
    return unproject_from_image(
        uv, depth, frame.intrinsics[i, cam].float(), frame.cam_to_ego[i, cam].float(), frame.img_aug[i, cam].float()
    )


def _to_current(batch: Batch, frame: Batch, k: int, i: int, points: Tensor) -> Tensor:
    """``(R, S, 3)`` points of sample ``i`` of ``frame`` (offset ``k``) in the current ego frame."""
    if k == 0:
        return points
    src_to_dst = (invert_pose(batch.ego_to_global[i].double()) @ frame.ego_to_global[i].double()).float()
    return transform_points(src_to_dst, points.reshape(-1, 3)).reshape(points.shape)


class RenderSupervision(SupervisionSource):
    """Rendering supervision over any queryable (temporal, for a window) head: QueryOcc's rendering-only
    ablation, the rival of ``queryocc_query_points`` on the same field, pseudo labels and query budget.

    Fairness: the defaults query the head ``rays_per_sample x samples_per_ray = 256 x 32 = 8192`` times per
    sample and step, exactly ``queryocc_query_points``' default ``points_per_sample x (negatives + positives) =
    1024 x (4 + 4)``; the pixels are drawn from the same pseudo depth / pseudo semantics (same
    ``frame_offsets``, ``pixel_stride``, ``max_depth``, ``long_range`` / ``near_range``), uniformly with
    replacement as ``queryocc_query_points`` draws its points.

    Args:
        weight: scale the model applies to every term.
        query_head: config name of the head to query.
        frame_offsets: frames the rays come from (``[0]``: the current frame's cameras; others must be in
            ``data.adjacent_offsets``; their rays are moved into the current ego frame, queried at their time).
        rays_per_sample: pixels (rays) drawn per sample and step; samples_per_ray: queries along each.
        near, far: the sampled camera-depth interval, metres; the leftover transmittance renders at ``far``.
        long_range: draw pixels whose pseudo point lies beyond the near field too; near_range: its
            half-extent in x and y (metres, current ego frame) when ``long_range`` is off.
        pixel_stride: subsampling of the pseudo depth maps before drawing.
        max_depth: pixels with a deeper pseudo depth are not drawn (metres).
        spacing: ``log`` (bins of equal depth ratio) or ``uniform`` stratified samples along each ray.
        sky_rays: further rays per sample through pixels whose pseudo class is ``free_label`` (sky), rendered
            against the far bound (free all the way, no semantic term): the same information the query source's
            ``sky_rays`` gives it, so the comparison stays fair (0, the default: none).
        lambda_depth, lambda_sem: the loss weights (depth: relative L1 ``|D - d*| / d*`` of camera z, scale-free
            like the semantic term, so far pixels do not outweigh near ones; sem: negative log likelihood of the
            rendered class distribution).

    Returns ``{"depth": L1, "sem": NLL}``, already times their lambdas.
    """

    needs_temporal_queries = False

    def __init__(
        self,
        weight: Annotated[float, NonNegative] = 1.0,
        query_head: str = "occupancy",
        frame_offsets: Annotated[list[Annotated[int, Range(low=-8, high=8)]], Length(min=1)] = [0],  # noqa: B006 - read only
        rays_per_sample: Annotated[int, Positive] = 256,
        samples_per_ray: Annotated[int, Positive] = 32,
        near: Annotated[float, Positive] = 1.0,
        far: Annotated[float, Positive] = 80.0,
        long_range: bool = True,
        near_range: Annotated[float, Positive] = 24.0,
        pixel_stride: Annotated[int, Positive] = 1,
        max_depth: Annotated[float, Positive] = 1000.0,
        lambda_depth: Annotated[float, NonNegative] = 1.0,
        lambda_sem: Annotated[float, NonNegative] = 1.0,
        spacing: Literal["log", "uniform"] = "log",
        sky_rays: Annotated[int, NonNegative] = 0,
        free_label: int | None = 17,
        ignore_label: int | None = 255,
    ) -> None:
        super().__init__()
        if sky_rays > 0 and free_label is None:
            raise ValueError("queryocc_render_points: sky_rays > 0 needs a free_label (the class sky pixels map to)")
        check_choices(RenderSupervision.__init__, "queryocc_render_points", spacing=spacing)
        self.log_spacing = spacing == "log"
        if not far > near:
            raise ValueError(f"queryocc_render_points needs far > near, got near={near}, far={far}")
        self.weight, self.query_head = float(weight), query_head
        self.frame_offsets = sorted({int(k) for k in frame_offsets})
        self.needs_temporal_queries = any(k != 0 for k in self.frame_offsets)
        self.rays_per_sample, self.samples_per_ray = int(rays_per_sample), int(samples_per_ray)
        self.near, self.far = float(near), float(far)
        self.long_range, self.near_range = bool(long_range), float(near_range)
        self.pixel_stride, self.max_depth = int(pixel_stride), float(max_depth)
        self.lambda_depth, self.lambda_sem = float(lambda_depth), float(lambda_sem)
        self.ignore_label = 255 if ignore_label is None else int(ignore_label)
        self.free_label = free_label
        self.sky_rays = int(sky_rays)
        self.requires = frozenset({"pseudo_depth", "pseudo_semantics"})

    @classmethod
    def conformance_outputs(cls, batch: Batch, grid, channels: int) -> ModelOutputs:
        """A query decoder over a random BEV plane on ``grid``, as for ``queryocc_query_points``."""

        return QuerySupervision.conformance_outputs(batch, grid, channels)

    def rays(self, batch: Batch) -> RaySet:
        """This step's sampled rays (uses the global RNG; seeded runs repeat)."""
        return sample_rays(
            batch,
            self.frame_offsets,
            self.rays_per_sample,
            self.samples_per_ray,
            self.near,
            self.far,
            self.ignore_label,
            self.pixel_stride,
            self.max_depth,
            None if self.long_range else self.near_range,
            log_spacing=self.log_spacing,
            sky_rays=self.sky_rays,
            free_label=self.free_label,
        )

    def forward(self, batch: Batch, outputs: ModelOutputs) -> dict[str, Tensor]:
        rays = self.rays(batch)
        b, r, s = rays.depths.shape
        times = rays.times[:, :, None].expand(b, r, s).reshape(b, r * s) if self.needs_temporal_queries else None
        result = outputs.query(self.query_head, rays.points.reshape(b, r * s, 3), times)
        if result.occupancy_logit is None:
            raise ValueError(f"queryocc_render_points: model.heads.{self.query_head} returns no occupancy logit")
        rendered = render_rays(
            result.occupancy_logit.float().reshape(b, r, s),
            result.class_logits.reshape(b, r, s, -1),
            rays.depths,
            self.far,
            self.free_label,
        )
        valid = rays.valid.float()
        target = rays.target_depth.clamp_max(self.far)
        out: dict[str, Tensor] = {}
        relative = (rendered.depth - target).abs() / target.clamp_min(self.near)
        out["depth"] = self.lambda_depth * (relative * valid).sum() / valid.sum().clamp_min(1)
        labels = rays.labels
        k = result.class_logits.shape[-1]
        has_free = self.free_label is not None and 0 <= self.free_label < k
        labelled = rays.valid & (labels != self.ignore_label) & (labels >= 0) & (labels < k)
        labelled &= rays.target_depth <= self.far
        if has_free:
            labelled &= labels != self.free_label
            labels = labels - (labels > self.free_label).long()  # index among the classes other than free
        if bool(labelled.any()):
            picked = rendered.log_probs.gather(-1, torch.where(labelled, labels, 0).unsqueeze(-1)).squeeze(-1)
            out["sem"] = -self.lambda_sem * picked[labelled].mean()
        else:
            out["sem"] = rendered.log_probs.sum() * 0.0
        return out
