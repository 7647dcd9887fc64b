"""Analytic solids of the synthetic world: boxes, vertical cylinders and vertical spheroids.

Every solid has a centre ``c``, half-extents ``h = (hx, hy, hz)`` and a heading ``yaw`` about +z.
Its *local* frame is centred on ``c`` and rotated by ``yaw``; dividing local coordinates by ``h``
gives the *unit* frame, in which the solid is the unit cube ``|u|_inf <= 1`` (box), the unit
cylinder ``u_x^2 + u_y^2 <= 1, |u_z| <= 1`` (cylinder) or the unit ball (spheroid). Cylinders are
circular (``hx == hy``) and spheroids symmetric about the vertical axis (``hx == hy``): that keeps
the voxel-overlap test of :func:`overlaps_voxels` exact.

All coordinates are metres in whatever frame the solids are expressed in (world or ego).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import torch
from torch import Tensor

__all__ = ["BOX", "CYLINDER", "SPHEROID", "Primitives", "RayHit", "intersect_rays"]

BOX, CYLINDER, SPHEROID = 0, 1, 2

# Hits closer than this to the ray origin are ignored (no self-intersection of secondary rays).
_T_MIN = 1e-4
# Ray x solid pairs evaluated at once; bounds memory to a few hundred MB on big images.
_PAIRS_PER_CHUNK = 1 << 21


@dataclass
class Primitives:
    """A batch of ``P`` solids with their semantics and appearance.

    Attributes:
        shape: ``(P,)`` int64, :data:`BOX`, :data:`CYLINDER` or :data:`SPHEROID`.
        center: ``(P, 3)`` float32 centre, metres.
        half: ``(P, 3)`` float32 half-extents along the local axes, metres.
        yaw: ``(P,)`` float32 heading about +z, radians.
        label: ``(P,)`` int64 Occ3D class id.
        instance: ``(P,)`` int64 track id of the agent the solid belongs to, ``-1`` if static.
        material: ``(P,)`` int64 appearance material (:mod:`.appearance`).
        color: ``(P, 3)`` float32 base albedo in [0, 1].
    """

    shape: Tensor
    center: Tensor
    half: Tensor
    yaw: Tensor
    label: Tensor
    instance: Tensor
    material: Tensor
    color: Tensor

    def __len__(self) -> int:
        return int(self.shape.shape[0])

    @staticmethod
    def empty() -> Primitives:
        """No solids."""
        z = torch.zeros(0, dtype=torch.int64)
        return Primitives(z, torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0), z, z, z, torch.zeros(0, 3))

    @staticmethod
    def from_rows(rows: Sequence[dict]) -> Primitives:
        """Build from dicts with keys ``shape, center, half, yaw, label, instance, material, color``."""
        if not rows:
            return Primitives.empty()
        return Primitives(
            shape=torch.tensor([r["shape"] for r in rows], dtype=torch.int64),
            center=torch.tensor([r["center"] for r in rows], dtype=torch.float32),
            half=torch.tensor([r["half"] for r in rows], dtype=torch.float32),
            yaw=torch.tensor([r.get("yaw", 0.0) for r in rows], dtype=torch.float32),
            label=torch.tensor([r["label"] for r in rows], dtype=torch.int64),
            instance=torch.tensor([r.get("instance", -1) for r in rows], dtype=torch.int64),
            material=torch.tensor([r["material"] for r in rows], dtype=torch.int64),
            color=torch.tensor([r["color"] for r in rows], dtype=torch.float32),
        )

    @staticmethod
    def cat(parts: Sequence[Primitives]) -> Primitives:
        """Concatenate batches."""
        return Primitives(**{f.name: torch.cat([getattr(p, f.name) for p in parts]) for f in fields(Primitives)})

    def select(self, index: Tensor) -> Primitives:
        """The solids at ``index`` (bool mask or int64 indices)."""
        return Primitives(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    def transformed(self, pose: Tensor) -> Primitives:
        """The solids expressed in another frame: ``pose`` ``(4, 4)`` maps their current frame into
        the new one and must rotate about z only (world <-> ego). Computed in float64."""
        pose = pose.to(torch.float64)
        center = self.center.to(torch.float64) @ pose[:3, :3].T + pose[:3, 3]
        yaw = math.atan2(float(pose[1, 0]), float(pose[0, 0]))
        out = self.select(slice(None))
        out.center = center.to(torch.float32)
        out.yaw = (self.yaw.to(torch.float64) + yaw).to(torch.float32)
        return out

    def bounding_radius(self) -> Tensor:
        """``(P,)`` radius of a sphere around each centre enclosing the solid."""
        return self.half.norm(dim=-1)

    def aabb(self) -> tuple[Tensor, Tensor]:
        """``(P, 3)`` lower and upper corners of each solid's axis-aligned bounding box."""
        c, s = self.yaw.cos().abs(), self.yaw.sin().abs()
        hx, hy, hz = self.half.unbind(-1)
        is_box = self.shape == BOX
        ex = torch.where(is_box, c * hx + s * hy, hx)  # round solids: hx == hy, rotation-invariant
        ey = torch.where(is_box, s * hx + c * hy, hy)
        ext = torch.stack([ex, ey, hz], -1)
        return self.center - ext, self.center + ext

    def to_local(self, points: Tensor) -> Tensor:
        """Points ``(..., P, 3)`` (or ``(..., 3)`` broadcast against ``P``) in each solid's local frame."""
        d = points - self.center
        c, s = self.yaw.cos(), self.yaw.sin()
        return torch.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1], d[..., 2]], -1)

    def contains(self, points: Tensor) -> Tensor:
        """``(..., P)`` bool: whether each point lies inside (or on) each solid.

        Args:
            points: ``(..., P, 3)`` or broadcastable to it, same frame as the solids.
        """
        u = self.to_local(points) / self.half
        box = u.abs().amax(-1) <= 1
        cyl = (u[..., :2].square().sum(-1) <= 1) & (u[..., 2].abs() <= 1)
        ball = u.square().sum(-1) <= 1
        return torch.where(self.shape == BOX, box, torch.where(self.shape == CYLINDER, cyl, ball))


@dataclass
class RayHit:
    """The nearest solid hit by each of ``R`` rays.

    Attributes:
        t: ``(R,)`` float32 distance along the unit ray, metres; ``inf`` for no hit.
        index: ``(R,)`` int64 index of the hit solid, ``-1`` for no hit.
        normal_unit: ``(R, 3)`` float32 outward normal at the hit in the solid's *unit* frame
            (zero for no hit); see :func:`local_normal`.
    """

    t: Tensor
    index: Tensor
    normal_unit: Tensor


def _safe(d: Tensor) -> Tensor:
    """Direction components bounded away from zero (keeps slab and cap divisions finite); the sign
    of a vanishing component does not matter to the tests that use it."""
    return torch.where(d.abs() < 1e-12, 1e-12, d)


def _box_hits(o: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
    """Unit cube: ``(R, P)`` entry distances (inf = miss) and entry axis (0..2)."""
    inv = 1.0 / _safe(d)
    t1, t2 = (-1.0 - o) * inv, (1.0 - o) * inv
    near, axis = torch.minimum(t1, t2).max(-1)
    far = torch.maximum(t1, t2).amin(-1)
    ok = (near <= far) & (near > _T_MIN)
    return torch.where(ok, near, torch.inf), axis


def _cylinder_hits(o: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
    """Unit cylinder: ``(R, P)`` entry distances and whether the entry is through a cap."""
    a = d[..., 0].square() + d[..., 1].square()
    b = o[..., 0] * d[..., 0] + o[..., 1] * d[..., 1]
    c = o[..., 0].square() + o[..., 1].square() - 1.0
    disc = b.square() - a * c
    t_side = (-b - disc.clamp_min(0).sqrt()) / a.clamp_min(1e-12)
    side_ok = (disc >= 0) & (a > 1e-12) & (t_side > _T_MIN) & ((o[..., 2] + t_side * d[..., 2]).abs() <= 1)
    dz = _safe(d[..., 2])
    t_cap = (-torch.sign(dz) - o[..., 2]) / dz  # the cap facing the ray
    xy = o[..., :2] + t_cap[..., None] * d[..., :2]
    cap_ok = (t_cap > _T_MIN) & (xy.square().sum(-1) <= 1)
    t_side = torch.where(side_ok, t_side, torch.inf)
    t_cap = torch.where(cap_ok, t_cap, torch.inf)
    return torch.minimum(t_side, t_cap), t_cap < t_side


def _ball_hits(o: Tensor, d: Tensor) -> Tensor:
    """Unit ball: ``(R, P)`` entry distances."""
    a = d.square().sum(-1)
    b = (o * d).sum(-1)
    c = o.square().sum(-1) - 1.0
    disc = b.square() - a * c
    t = (-b - disc.clamp_min(0).sqrt()) / a
    return torch.where((disc >= 0) & (t > _T_MIN), t, torch.inf)


def _nearest_of_kind(kind: int, o: Tensor, d: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """For rays ``d`` ``(R, P, 3)`` and origins ``o`` ``(R or 1, P, 3)`` in unit frames of ``P``
    solids of one kind: nearest ``t`` ``(R,)``, its solid ``(R,)`` and unit-frame normal ``(R, 3)``."""
    rows = torch.arange(d.shape[0], device=d.device)
    if kind == BOX:
        t, axis = _box_hits(o, d)
        t_min, j = t.min(-1)
        axis = axis[rows, j]
        normal = torch.zeros(d.shape[0], 3, dtype=d.dtype, device=d.device)
        normal[rows, axis] = -torch.sign(d[rows, j, axis])  # entry face faces the ray
        return t_min, j, normal
    if kind == CYLINDER:
        t, cap = _cylinder_hits(o, d)
        t_min, j = t.min(-1)
        oj = o.expand_as(d)[rows, j]
        p = oj + t_min.clamp(max=1e30)[:, None] * d[rows, j]
        side = torch.cat([p[:, :2], torch.zeros_like(p[:, :1])], -1)
        top = torch.zeros_like(p)
        top[:, 2] = -torch.sign(d[rows, j, 2])
        return t_min, j, torch.where(cap[rows, j][:, None], top, side)
    t = _ball_hits(o, d)
    t_min, j = t.min(-1)
    p = o.expand_as(d)[rows, j] + t_min.clamp(max=1e30)[:, None] * d[rows, j]
    return t_min, j, p


def intersect_rays(prims: Primitives, origin: Tensor, directions: Tensor, bundles: Tensor | None = None,
                   limit: Tensor | None = None, cull: bool = True) -> RayHit:
    """The nearest solid along rays sharing one origin (a camera or a LiDAR).

    Rays are processed in *bundles* (e.g. image tiles or azimuth sectors): for each bundle, solids
    whose bounding sphere lies outside the cone spanned by its rays are culled, and the rest are
    intersected exactly, batched per solid kind.

    Args:
        prims: ``P`` solids, in the rays' frame.
        origin: ``(3,)`` common ray origin, metres.
        directions: ``(R, 3)`` unit directions.
        bundles: ``(R,)`` int64 bundle id of each ray (coherent rays share an id); None = one bundle.
        limit: ``(R,)`` distances beyond which a ray's hits do not matter (e.g. where it meets the
            ground); solids entirely beyond a whole bundle's limits are culled too. Hits beyond a
            ray's limit may still be reported.
        cull: False skips the culling (for tests).

    Returns:
        :class:`RayHit`; ``index`` refers to ``prims``.
    """
    r = directions.shape[0]
    best = RayHit(
        t=torch.full((r,), torch.inf), index=torch.full((r,), -1, dtype=torch.int64), normal_unit=torch.zeros(r, 3)
    )
    if len(prims) == 0 or r == 0:
        return best
    if bundles is None:
        bundles = torch.zeros(r, dtype=torch.int64)
    if limit is None:
        limit = torch.full((r,), torch.inf)
    near = (prims.center - origin).norm(dim=-1) - prims.bounding_radius()  # closest possible hit
    # per kind, everything that does not depend on the rays
    groups = []
    for kind in (BOX, CYLINDER, SPHEROID):
        ids = torch.nonzero(prims.shape == kind).squeeze(1)
        if ids.numel():
            sub = prims.select(ids)
            o_unit = sub.to_local(origin[None]) / sub.half  # (P, 3)
            groups.append((kind, ids, sub, o_unit, sub.yaw.cos(), sub.yaw.sin()))
    order = torch.argsort(bundles, stable=True)
    start = 0
    for size in torch.bincount(bundles).tolist():
        rows = order[start : start + size]
        start += size
        if size == 0:
            continue
        dirs = directions[rows]
        t_best, i_best, n_best = best.t[rows], best.index[rows], best.normal_unit[rows]
        if cull:
            visible = _in_cone(prims, origin, dirs) & (near <= limit[rows].max())
        else:
            visible = torch.ones(len(prims), dtype=torch.bool)
        for kind, ids, sub, o_unit, cos, sin in groups:
            keep = visible[ids]
            if not keep.any():
                continue
            o, c, s, half = o_unit[keep][None], cos[keep], sin[keep], sub.half[keep]
            for chunk in torch.split(torch.arange(size), max(1, _PAIRS_PER_CHUNK // int(keep.sum()))):
                d = dirs[chunk][:, None, :]
                d_local = torch.stack(
                    [c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1], d[..., 2].expand(-1, c.numel())], -1
                )
                t, j, n = _nearest_of_kind(kind, o, d_local / half)
                closer = t < t_best[chunk]
                t_best[chunk] = torch.where(closer, t, t_best[chunk])
                i_best[chunk] = torch.where(closer, ids[keep][j], i_best[chunk])
                n_best[chunk] = torch.where(closer[:, None], n, n_best[chunk])
        best.t[rows], best.index[rows], best.normal_unit[rows] = t_best, i_best, n_best
    return best


def _in_cone(prims: Primitives, origin: Tensor, directions: Tensor) -> Tensor:
    """``(P,)`` bool: the solid's bounding sphere may meet a ray of the bundle (conservative)."""
    axis = directions.mean(0)
    axis = axis / axis.norm().clamp_min(1e-9)
    cos_half = (directions @ axis).min().clamp(-1, 1)
    half_angle = torch.arccos(cos_half)
    to_c = prims.center - origin
    dist = to_c.norm(dim=-1)
    radius = prims.bounding_radius()
    inside = dist <= radius
    cos_c = ((to_c @ axis) / dist.clamp_min(1e-9)).clamp(-1, 1)
    angle = torch.arccos(cos_c) - torch.arcsin((radius / dist.clamp_min(1e-9)).clamp(max=1.0))
    return inside | (angle <= half_angle + 1e-4)


def local_normal(prims: Primitives, index: Tensor, normal_unit: Tensor) -> Tensor:
    """Unit normals ``(R, 3)`` in the solids' frame (not local): the unit-frame normal scaled by
    ``1 / half`` (normals transform by the inverse scale) and rotated by the solid's yaw."""
    n = normal_unit / prims.half[index]
    yaw = prims.yaw[index]
    c, s = yaw.cos(), yaw.sin()
    n = torch.stack([c * n[:, 0] - s * n[:, 1], s * n[:, 0] + c * n[:, 1], n[:, 2]], -1)
    return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def overlaps_voxels(prims: Primitives, k: int, lower: Tensor, upper: Tensor) -> Tensor:
    """Whether solid ``k`` meets each axis-aligned box (closed sets, exact).

    Args:
        prims: the solids; ``k`` selects one.
        lower, upper: ``(..., 3)`` corners of the boxes (voxels), same frame as the solids.

    Returns:
        ``(...)`` bool.
    """
    c, h, shape = prims.center[k], prims.half[k], int(prims.shape[k])
    z_ok = (lower[..., 2] <= c[2] + h[2]) & (upper[..., 2] >= c[2] - h[2])
    if shape == BOX:
        # Separating axes in the plane: the voxel's x, y and the box's heading axes.
        yaw = prims.yaw[k]
        cy, sy = torch.cos(yaw), torch.sin(yaw)
        ext_x = cy.abs() * h[0] + sy.abs() * h[1]
        ext_y = sy.abs() * h[0] + cy.abs() * h[1]
        ok = (lower[..., 0] <= c[0] + ext_x) & (upper[..., 0] >= c[0] - ext_x)
        ok &= (lower[..., 1] <= c[1] + ext_y) & (upper[..., 1] >= c[1] - ext_y)
        mid = (lower[..., :2] + upper[..., :2]) / 2 - c[:2]
        rad = (upper[..., :2] - lower[..., :2]) / 2
        for axis, extent in (((cy, sy), h[0]), ((-sy, cy), h[1])):
            proj = (mid[..., 0] * axis[0] + mid[..., 1] * axis[1]).abs()
            reach = rad[..., 0] * axis[0].abs() + rad[..., 1] * axis[1].abs()
            ok &= proj <= extent + reach
        return ok & z_ok
    if shape == CYLINDER:
        nearest = torch.maximum(torch.minimum(c[:2], upper[..., :2]), lower[..., :2])
        return z_ok & ((nearest - c[:2]).square().sum(-1) <= h[0] ** 2)
    # spheroid: scaling z by hx / hz turns it into a ball and keeps the voxel axis-aligned
    scale = torch.stack([h[0], h[0], h[2]])
    lo, hi, cc = lower / scale, upper / scale, c / scale
    nearest = torch.maximum(torch.minimum(cc, hi), lo)
    return (nearest - cc).square().sum(-1) <= 1.0
