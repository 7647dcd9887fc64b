"""QueryOcc's query supervision source ``queryocc_query_points`` (the method), and the labelled points and sky
rays of a temporal window in the current ego frame that both supervision sources read.

QueryOcc's 4D query self-supervision (§3.1). From each labelled point ``p`` seen from ``o`` (pseudo points from
depth maps, LiDAR returns, or both; :mod:`occplug.data.labelled_points`), in the current frame or an adjacent one
moved into the current ego frame with the poses (the query keeps its own time ``t``):

* **negatives** ``o + r (p - o)``, ``r ~ U(0, 1)``: the ray crossed them, so they are free;
* **positives** ``p + r (p - o) / |p - o|``, ``r ~ U(0, zeta)``: just behind the surface, occupied, with
  the point's class (and feature).

Negatives train the occupancy loss only; positives train occupancy, semantics and (with features)
the L1 feature loss: ``L = l_occ BCE(o, occ) + l_sem CE(s, class) + l_vfm L1(v, feature)``.

* **sky negatives** (``sky_rays > 0``; this project's reading, the paper is silent): a pixel whose pseudo
  class is free (a segmenter's ``sky`` mapped to ``free``) has no point, so the two rules above give its
  ray no query. Its ray is free as far as the camera sees: ``o + r d``, ``r ~ U(0, r_max)``, with ``r_max``
  the smaller of ``sky_far`` and the distance at which the ray leaves the grid's height range, are
  negatives too. Without them, the air cameras look through above the horizon gets no query at all.

The rendering-only rival, ``queryocc_render_points``, is :mod:`.render_points`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from occplug.constraints import Length, NonNegative, Positive, Range, check_choices
from occplug.data import Batch, LabelledPoints, free_pixel_rays, lidar_points, pseudo_depth_points, to_frame
from occplug.geometry import GridSpec
from occplug.interfaces import ModelOutputs, SupervisionSource

__all__ = [
    "QuerySet",
    "QuerySupervision",
    "in_current_frame",
    "sample_queries",
    "sample_sky_negatives",
    "sample_surface_negatives",
    "sky_rays",
    "supervision_points",
]


def supervision_points(
    batch: Batch,
    source: str,
    offsets: list[int],
    ignore_label: int,
    pixel_stride: int = 1,
    with_features: bool = False,
    max_depth: float = float("inf"),
) -> list[tuple[LabelledPoints, Tensor]]:
    """Per sample: the labelled points of every frame offset in ``offsets``, in the current ego frame, with
    ``(P,)`` times (seconds relative to the current frame).

    Args:
        source: ``pseudo`` (pseudo depth + pseudo semantics), ``lidar`` (returns labelled through the 2D
            pseudo semantics) or ``union``.
        offsets: frame offsets (0: the current frame; others must be in ``batch.adjacent``).
    """

    def frame_points(frame: Batch) -> list[LabelledPoints]:
        sets: list[list[LabelledPoints]] = []
        if source in ("pseudo", "union"):
            sets.append(pseudo_depth_points(frame, pixel_stride, max_depth, ignore_label, with_features))
        if source in ("lidar", "union"):
            sets.append(lidar_points(frame, ignore_label))
        out = []
        for i in range(len(batch)):
            parts = [s[i] for s in sets]
            if with_features and source == "union":  # LiDAR points carry no features: drop them from the L1 term
                parts = [p if p.features is not None else _zero_features(p, parts[0]) for p in parts]
            out.append(LabelledPoints.cat(parts))
        return out

    return in_current_frame(batch, offsets, frame_points)


def sky_rays(
    batch: Batch, offsets: list[int], free_label: int, pixel_stride: int = 1
) -> list[tuple[LabelledPoints, Tensor]]:
    """Per sample: the rays of the pixels whose pseudo class is free (sky) in every frame offset of ``offsets``,
    in the current ego frame (:func:`~occplug.data.free_pixel_rays`: a point one metre along each ray), with
    ``(R,)`` times (seconds relative to the current frame)."""
    return in_current_frame(batch, offsets, lambda frame: free_pixel_rays(frame, free_label, pixel_stride))


def in_current_frame(
    batch: Batch, offsets: list[int], make: Callable[[Batch], list[LabelledPoints]]
) -> list[tuple[LabelledPoints, Tensor]]:
    """Per sample: ``make(frame)``'s points of every frame offset in ``offsets``, moved into the current ego frame,
    with ``(P,)`` times (seconds relative to the current frame).

    At a scene's ends the data clamps an adjacent frame to the current one (:meth:`~occplug.data.SceneIndex.neighbour`:
    the same token); such a frame is left out, so a sample there uses only the neighbours that exist and no
    frame is counted twice as if it were another time.
    """
    per_sample: list[list[tuple[LabelledPoints, Tensor]]] = [[] for _ in range(len(batch))]
    for k in offsets:
        frame = batch if k == 0 else batch.adjacent.get(k)
        if frame is None:
            raise ValueError(
                f"queryocc_query_points: frame offset {k} is not loaded (set data.adjacent_offsets to include {k})"
            )
        for i, pts in enumerate(make(frame)):
            if k != 0 and frame.token[i] == batch.token[i]:  # clamped at the scene's end: the current frame again
                pts = pts.select(torch.zeros(len(pts), dtype=torch.bool, device=pts.points.device))
            elif k != 0:
                pts = to_frame(pts, frame.ego_to_global[i], batch.ego_to_global[i])
            dt = float(frame.timestamp[i] - batch.timestamp[i]) if k != 0 else 0.0
            per_sample[i].append((pts, torch.full((len(pts),), dt, device=pts.points.device)))
    return [(LabelledPoints.cat([p for p, _ in parts]), torch.cat([t for _, t in parts])) for parts in per_sample]


def _zero_features(points: LabelledPoints, like: LabelledPoints) -> LabelledPoints:
    dim = like.features.shape[1] if like.features is not None else 0
    nan = torch.full((len(points), dim), float("nan"), device=points.points.device)
    return LabelledPoints(points.points, points.origins, points.labels, nan)


class QuerySet:
    """Sampled queries of one batch: ``points`` ``(B, Q, 3)``, ``times`` ``(B, Q)``, ``occupied`` ``(B, Q)`` bool,
    ``labels`` ``(B, Q)`` int64 (``ignore`` for negatives), ``features`` ``(B, Q, F)`` or ``None`` (NaN: no target),
    ``valid`` ``(B, Q)`` bool (False: a placeholder of a sample without points, in no loss)."""

    def __init__(
        self, points: Tensor, times: Tensor, occupied: Tensor, labels: Tensor, features: Tensor | None, valid: Tensor
    ):
        self.points, self.times, self.occupied, self.labels, self.features = points, times, occupied, labels, features
        self.valid = valid

    def cat(self, other: QuerySet) -> QuerySet:
        """Both sets' queries per sample (``other`` after ``self``; features NaN where a set has none)."""
        feats = None
        if self.features is not None or other.features is not None:
            like = self.features if self.features is not None else other.features
            feats = torch.cat(
                [_nan_features(q, like.shape[-1]) if q.features is None else q.features for q in (self, other)], 1
            )
        return QuerySet(
            torch.cat([self.points, other.points], 1),
            torch.cat([self.times, other.times], 1),
            torch.cat([self.occupied, other.occupied], 1),
            torch.cat([self.labels, other.labels], 1),
            feats,
            torch.cat([self.valid, other.valid], 1),
        )


def _nan_features(queries: QuerySet, dim: int) -> Tensor:
    return torch.full((*queries.points.shape[:2], dim), float("nan"), device=queries.points.device)


def sample_queries(
    sets: list[tuple[LabelledPoints, Tensor]],
    points_per_sample: int,
    negatives: int,
    positives: int,
    zeta: float,
    ignore_label: int,
    generator: torch.Generator | None = None,
) -> QuerySet:
    """Draw ``points_per_sample`` points per sample (with replacement) and ``negatives`` + ``positives`` queries
    from each (see the module docstring). A sample without points gets placeholder queries at the origin with
    ``valid`` False (the losses leave them out)."""
    qs, ts, occ, labels, feats, valid = [], [], [], [], [], []
    has_features = all(s.features is not None for s, _ in sets)
    device = sets[0][0].points.device
    for pts, times in sets:
        n = len(pts)
        valid.append(torch.full((points_per_sample * (negatives + positives),), n > 0, device=device))
        if n == 0:
            pts = LabelledPoints(
                torch.zeros(1, 3, device=device),
                torch.zeros(1, 3, device=device),
                torch.full((1,), ignore_label, dtype=torch.int64, device=device),
                None
                if not has_features
                else torch.full((1, sets[0][0].features.shape[1]), float("nan"), device=device),
            )
            times, n = torch.zeros(1, device=device), 1
        pick = torch.randint(0, n, (points_per_sample,), generator=generator).to(device)
        p, o = pts.points[pick], pts.origins[pick]
        ray = p - o
        r_neg = torch.rand(points_per_sample, negatives, generator=generator).to(device)
        r_pos = torch.rand(points_per_sample, positives, generator=generator).to(device) * zeta
        neg = o[:, None] + r_neg[..., None] * ray[:, None]
        unit = ray / ray.norm(dim=-1, keepdim=True).clamp_min(1e-6)
        pos = p[:, None] + r_pos[..., None] * unit[:, None]
        qs.append(torch.cat([neg.reshape(-1, 3), pos.reshape(-1, 3)]))
        t = times[pick]
        ts.append(torch.cat([t.repeat_interleave(negatives), t.repeat_interleave(positives)]))
        occ.append(
            torch.cat(
                [
                    torch.zeros(points_per_sample * negatives, dtype=torch.bool, device=device),
                    torch.ones(points_per_sample * positives, dtype=torch.bool, device=device),
                ]
            )
        )
        lab = pts.labels[pick]
        labels.append(
            torch.cat(
                [
                    torch.full((points_per_sample * negatives,), ignore_label, device=device, dtype=torch.int64),
                    lab.repeat_interleave(positives),
                ]
            )
        )
        if has_features:
            f = pts.features[pick]
            feats.append(
                torch.cat(
                    [
                        torch.full((points_per_sample * negatives, f.shape[1]), float("nan"), device=device),
                        f.repeat_interleave(positives, dim=0),
                    ]
                )
            )
    return QuerySet(
        torch.stack(qs),
        torch.stack(ts),
        torch.stack(occ),
        torch.stack(labels),
        torch.stack(feats) if has_features else None,
        torch.stack(valid),
    )


def sample_surface_negatives(
    sets: list[tuple[LabelledPoints, Tensor]],
    points_per_sample: int,
    negatives: int,
    zeta: float,
    ignore_label: int,
    generator: torch.Generator | None = None,
) -> QuerySet:
    """Free queries just in front of the points: ``points_per_sample`` points per sample (with replacement, drawn
    anew) and ``negatives`` queries ``p - r (p - o) / |p - o|``, ``r ~ U(0, min(zeta, |p - o|))`` on each: the
    mirror of the positives' buffer behind the point, on the part of the ray the sensor saw through. A sample
    without points gets placeholder queries with ``valid`` False.

    Returns a :class:`QuerySet` of ``points_per_sample * negatives`` free queries per sample (labels ``ignore``).
    """

    def draw(pts: LabelledPoints, times: Tensor) -> tuple[Tensor, Tensor]:
        pick = torch.randint(0, len(pts), (points_per_sample,), generator=generator).to(pts.points.device)
        p, o = pts.points[pick], pts.origins[pick]
        length = (p - o).norm(dim=-1, keepdim=True)
        unit = (p - o) / length.clamp_min(1e-6)
        r = torch.rand(points_per_sample, negatives, generator=generator).to(p.device) * length.clamp_max(zeta)
        return (p[:, None] - r[..., None] * unit[:, None]).reshape(-1, 3), times[pick].repeat_interleave(negatives)

    return _free_queries(sets, points_per_sample * negatives, draw, ignore_label)


def _free_queries(
    sets: list[tuple[LabelledPoints, Tensor]],
    count: int,
    draw: Callable[[LabelledPoints, Tensor], tuple[Tensor, Tensor]],
    ignore_label: int,
) -> QuerySet:
    """A :class:`QuerySet` of ``count`` free queries per sample, ``draw(points, times)`` giving each non-empty
    sample's ``(count, 3)`` queries and ``(count,)`` times; an empty sample gets placeholders (``valid`` False)."""
    qs, ts, valid = [], [], []
    device = sets[0][0].points.device
    for pts, times in sets:
        valid.append(torch.full((count,), len(pts) > 0, device=device))
        q, t = (
            draw(pts, times) if len(pts) else (torch.zeros(count, 3, device=device), torch.zeros(count, device=device))
        )
        qs.append(q)
        ts.append(t)
    b = len(sets)
    return QuerySet(
        torch.stack(qs),
        torch.stack(ts),
        torch.zeros(b, count, dtype=torch.bool, device=device),
        torch.full((b, count), ignore_label, dtype=torch.int64, device=device),
        None,
        torch.stack(valid),
    )


def sample_sky_negatives(
    rays: list[tuple[LabelledPoints, Tensor]],
    rays_per_sample: int,
    negatives: int,
    far: float,
    heights: tuple[float, float],
    ignore_label: int,
    generator: torch.Generator | None = None,
) -> QuerySet:
    """Free queries along rays that end at no surface (:func:`sky_rays`): ``rays_per_sample`` rays per sample
    (with replacement) and ``negatives`` points ``o + r d`` on each, ``r ~ U(0, r_max)``, where ``r_max`` is
    ``far`` or, if sooner, where the ray leaves the height range ``heights = (z_min, z_max)`` (ego frame,
    metres; the scored grid's: higher queries teach nothing the evaluation sees). A sample without such rays
    gets placeholder queries with ``valid`` False.

    Returns a :class:`QuerySet` of ``rays_per_sample * negatives`` free queries per sample (labels ``ignore``).
    """
    z_lo, z_hi = heights

    def draw(pts: LabelledPoints, times: Tensor) -> tuple[Tensor, Tensor]:
        device = pts.points.device
        pick = torch.randint(0, len(pts), (rays_per_sample,), generator=generator).to(device)
        o = pts.origins[pick]
        d = pts.points[pick] - o  # unit directions
        dz = d[:, 2]
        up = (z_hi - o[:, 2]) / dz.clamp_min(1e-9)
        down = (z_lo - o[:, 2]) / dz.clamp_max(-1e-9)
        leave = torch.where(dz > 1e-9, up, torch.where(dz < -1e-9, down, torch.full_like(dz, far)))
        r_max = leave.clamp(0.0, far)
        r = torch.rand(rays_per_sample, negatives, generator=generator).to(device) * r_max[:, None]
        return (o[:, None] + r[..., None] * d[:, None]).reshape(-1, 3), times[pick].repeat_interleave(negatives)

    return _free_queries(rays, rays_per_sample * negatives, draw, ignore_label)


class QuerySupervision(SupervisionSource):
    """QueryOcc's query supervision over any queryable (temporal, for a window) head.

    Args:
        weight: scale the model applies to every term.
        query_head: config name of the head to query.
        points: ``pseudo``, ``lidar`` or ``union`` (see :func:`supervision_points`).
        frame_offsets: frames the points come from (``[0]``: the current frame only; ``[-1, 0, 1]`` the
            paper's temporal window; the others must be in ``data.adjacent_offsets``).
        points_per_sample: points drawn per sample and step; negatives, positives: queries per point.
        zeta: depth of the occupied buffer behind each point, metres.
        long_range: supervise with points beyond the near field too; near_range: its half-extent
            in x and y (metres, current ego frame) when ``long_range`` is off.
        pixel_stride: subsampling of the pseudo depth maps before drawing.
        max_depth: pseudo points deeper than this are dropped (metres).
        lambda_occ, lambda_sem, lambda_vfm: the loss weights; ``lambda_vfm > 0`` distils ``pseudo_features``
            into the head's ``features`` output.
        surface_negatives: further free queries per point within ``zeta`` in front of it
            (:func:`sample_surface_negatives`; 0, the default: none). The paper draws negatives uniformly along
            the whole segment; under a noisy depth a surface's positives then outnumber the negatives in front of
            it, and the field grows towards the sensor. This option puts some on the segment's last ``zeta``.
        sky_rays: rays per sample and step drawn from the pixels whose pseudo class is ``free_label`` (a
            segmenter's ``sky`` mapped to ``free``; :func:`sky_rays`), each giving ``sky_negatives`` free queries
            up to ``sky_far`` metres or where it leaves the grid's height range (:func:`sample_sky_negatives`);
            0 (the default): none. This project's reading, not the paper's: without it no query tells the
            field that the air cameras look through above the horizon is free.
        grid: the evaluation grid (given); its height range bounds the sky negatives.

    Returns ``{"occ": BCE, "sem": CE, "vfm": L1}`` (``vfm`` only when distilling), already times their lambdas.
    """

    needs_temporal_queries = False

    def __init__(
        self,
        weight: Annotated[float, NonNegative] = 1.0,
        query_head: str = "occupancy",
        points: Literal["pseudo", "lidar", "union"] = "pseudo",
        frame_offsets: Annotated[list[Annotated[int, Range(low=-8, high=8)]], Length(min=1)] = [0],  # noqa: B006 - read only
        points_per_sample: Annotated[int, Positive] = 1024,
        negatives: Annotated[int, NonNegative] = 4,
        positives: Annotated[int, NonNegative] = 4,
        zeta: Annotated[float, Positive] = 0.5,
        long_range: bool = True,
        near_range: Annotated[float, Positive] = 24.0,
        pixel_stride: Annotated[int, Positive] = 1,
        max_depth: Annotated[float, Positive] = 1000.0,
        lambda_occ: Annotated[float, NonNegative] = 1.0,
        lambda_sem: Annotated[float, NonNegative] = 1.0,
        lambda_vfm: Annotated[float, NonNegative] = 0.0,
        surface_negatives: Annotated[int, NonNegative] = 0,
        sky_rays: Annotated[int, NonNegative] = 0,
        sky_negatives: Annotated[int, Positive] = 4,
        sky_far: Annotated[float, Positive] = 80.0,
        grid: GridSpec | None = None,
        free_label: int | None = 17,
        ignore_label: int | None = 255,
    ) -> None:
        super().__init__()
        if sky_rays > 0 and free_label is None:
            raise ValueError("queryocc_query_points: sky_rays > 0 needs a free_label (the class sky pixels map to)")
        check_choices(QuerySupervision.__init__, "queryocc_query_points", points=points)
        if negatives + positives == 0:
            raise ValueError("queryocc_query_points needs negatives + positives > 0")
        self.weight, self.query_head, self.source = float(weight), query_head, points
        self.frame_offsets = sorted({int(k) for k in frame_offsets})
        self.needs_temporal_queries = any(k != 0 for k in self.frame_offsets)
        self.points_per_sample, self.negatives, self.positives = int(points_per_sample), int(negatives), int(positives)
        self.zeta, self.long_range, self.near_range = float(zeta), bool(long_range), float(near_range)
        self.pixel_stride, self.max_depth = int(pixel_stride), float(max_depth)
        self.lambda_occ, self.lambda_sem, self.lambda_vfm = float(lambda_occ), float(lambda_sem), float(lambda_vfm)
        self.ignore_label = 255 if ignore_label is None else int(ignore_label)
        self.free_label = free_label
        self.surface_negatives = int(surface_negatives)
        self.sky_rays, self.sky_negatives, self.sky_far = int(sky_rays), int(sky_negatives), float(sky_far)
        spec = grid
        self.heights = (spec.lower[2], spec.upper[2]) if spec is not None else (-float("inf"), float("inf"))
        needs = {"pseudo_semantics"}  # LiDAR points take their class from it too
        if points in ("pseudo", "union"):
            needs |= {"pseudo_depth"} | ({"pseudo_features"} if self.lambda_vfm > 0 else set())
        if points in ("lidar", "union"):
            needs |= {"points", "lidar_to_ego"}
        self.requires = frozenset(needs)

    @classmethod
    def conformance_outputs(cls, batch: Batch, grid, channels: int) -> ModelOutputs:
        """A query decoder over a random BEV plane on ``grid`` (the conformance model's head cannot be queried in time)."""
        from occplug.interfaces import BevScene

        from ..heads import QueryDecoder

        head = QueryDecoder(channels, num_classes=18, hidden=16)  # the tiny world's Occ3D classes
        scene = BevScene(torch.randn(len(batch), channels, *grid.shape[:2], requires_grad=True), grid)
        return ModelOutputs(
            image_features=None,
            lifted=None,
            scene=scene,
            heads={},
            query=lambda name, points, times=None: head.query(scene, points, times),
        )

    def queries(self, batch: Batch) -> QuerySet:
        """This step's sampled queries (uses the global RNG; seeded runs repeat)."""
        sets = supervision_points(
            batch,
            self.source,
            self.frame_offsets,
            self.ignore_label,
            self.pixel_stride,
            self.lambda_vfm > 0,
            self.max_depth,
        )
        if self.free_label is not None:  # a point of class free (e.g. sky given a depth) is no surface
            sets = [(p.select(keep), t[keep]) for p, t in sets for keep in [p.labels != self.free_label]]
        if not self.long_range:
            sets = [
                (p.select(keep), t[keep])
                for p, t in sets
                for keep in [(p.points[:, :2].abs() <= self.near_range).all(-1)]
            ]
        drawn = sample_queries(
            sets, self.points_per_sample, self.negatives, self.positives, self.zeta, self.ignore_label
        )
        if self.surface_negatives > 0:
            near = sample_surface_negatives(
                sets, self.points_per_sample, self.surface_negatives, self.zeta, self.ignore_label
            )
            drawn = drawn.cat(near)
        if self.sky_rays > 0:
            rays = sky_rays(batch, self.frame_offsets, self.free_label, self.pixel_stride)
            sky = sample_sky_negatives(
                rays, self.sky_rays, self.sky_negatives, self.sky_far, self.heights, self.ignore_label
            )
            drawn = drawn.cat(sky)
        return drawn

    def forward(self, batch: Batch, outputs: ModelOutputs) -> dict[str, Tensor]:
        q = self.queries(batch)
        result = outputs.query(self.query_head, q.points, q.times if self.needs_temporal_queries else None)
        out: dict[str, Tensor] = {}
        if result.occupancy_logit is None:
            raise ValueError(f"queryocc_query_points: model.heads.{self.query_head} returns no occupancy logit")
        valid = q.valid.float()
        bce = F.binary_cross_entropy_with_logits(result.occupancy_logit, q.occupied.float(), reduction="none")
        out["occ"] = self.lambda_occ * (bce * valid).sum() / valid.sum().clamp_min(1)
        keep = q.occupied & q.valid & (q.labels != self.ignore_label)
        labels = torch.where(keep, q.labels, torch.full_like(q.labels, -100))
        logits = result.class_logits.reshape(-1, result.class_logits.shape[-1])
        if bool((labels >= 0).any()):
            out["sem"] = self.lambda_sem * F.cross_entropy(logits, labels.reshape(-1), ignore_index=-100)
        else:
            out["sem"] = logits.sum() * 0.0
        if self.lambda_vfm > 0:
            if result.features is None or q.features is None:
                raise ValueError(
                    f"queryocc_query_points: lambda_vfm > 0 needs model.heads.{self.query_head}.feature_dim > 0 "
                    "and pseudo_features in the batch"
                )
            has = ~torch.isnan(q.features).any(-1) & q.valid
            diff = (result.features - torch.nan_to_num(q.features)).abs().mean(-1)
            out["vfm"] = self.lambda_vfm * (diff * has).sum() / has.sum().clamp_min(1)
        return out
