"""Scene generation: road layout, ground map, static structures, moving agents and the ego's path.

A scene lives in its own **world** frame (metres, z up, the ground is the plane ``z = 0``): a main
road runs along +x through the origin, traffic drives on the right (lanes heading +x at ``y < 0``),
and an optional cross road meets it at ``x = x_c``. The ego starts at the origin region at ``t = 0``
and drives along a lane at constant speed, either straight on or turning right into the cross road.
``Scene.world_to_global`` places the world in a global frame with a random heading and offset, so
``ego_to_global`` poses are not axis-aligned.

Everything is drawn from a NumPy generator seeded by ``(world seed, split, scene index)``: a scene is
a pure function of those, and scenes of different splits never share a seed.

Motion is exact and smooth: every agent moves at constant velocity along a straight line (lanes,
sidewalks), so velocities and positions of different frames agree to rounding error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .appearance import MATERIALS as M
from .config import SyntheticWorldConfig
from .primitives import BOX, CYLINDER, SPHEROID, Primitives

__all__ = ["Agents", "EgoPath", "GroundMap", "Scene", "build_scene"]

SPLIT_IDS = {"train": 0, "val": 1, "test": 2}

# Occ3D ids used here.
BARRIER, BICYCLE, BUS, CAR, CONSTRUCTION, MOTORCYCLE, PEDESTRIAN, CONE, TRAILER, TRUCK = 1, 2, 3, 4, 5, 6, 7, 8, 9, 10
ROAD, OTHER_FLAT, SIDEWALK, TERRAIN, MANMADE, VEGETATION = 11, 12, 13, 14, 15, 16

_RASTER_RES = 0.1  # metres per ground-map cell

# ----------------------------------------------------------------------------------------------
# Ground


@dataclass
class GroundMap:
    """The ground's semantic raster and its painted markings, in the world frame.

    Attributes:
        classes: ``(NX, NY)`` uint8 ground class of the cell ``[ix, iy]`` covering
            ``[x0 + ix * res, x0 + (ix + 1) * res) x [y0 + iy * res, ...)``; outside it: terrain.
        origin: ``(x0, y0)`` metres.
        resolution: ``res`` metres.
        markings: ``(S, 8)`` float32 painted rectangles ``x0, x1, y0, y1, dash_axis, period, on,
            paint``: ``dash_axis`` -1 for solid paint, 0/1 for a pattern repeating along x/y with
            ``period`` metres of which the first ``on`` are painted; ``paint`` 1 white, 2 yellow.
    """

    classes: Tensor
    origin: tuple[float, float]
    resolution: float
    markings: Tensor

    def classes_at(self, xy: Tensor) -> Tensor:
        """``(K,)`` int64 ground class at ``(K, 2)`` world points."""
        idx = torch.floor(
            (xy.to(torch.float64) - torch.tensor(self.origin, dtype=torch.float64)) / self.resolution
        ).long()
        nx, ny = self.classes.shape
        inside = (idx[:, 0] >= 0) & (idx[:, 0] < nx) & (idx[:, 1] >= 0) & (idx[:, 1] < ny)
        out = torch.full((xy.shape[0],), TERRAIN, dtype=torch.int64)
        out[inside] = self.classes[idx[inside, 0], idx[inside, 1]].long()
        return out

    def marking_at(self, xy: Tensor) -> Tensor:
        """``(K,)`` int64 paint at ``(K, 2)`` world points: 0 none, 1 white, 2 yellow."""
        out = torch.zeros(xy.shape[0], dtype=torch.int64)
        if xy.shape[0] == 0 or self.markings.shape[0] == 0:
            return out
        m = self.markings
        x, y = xy[:, 0:1], xy[:, 1:2]
        inside = (x >= m[:, 0]) & (x < m[:, 1]) & (y >= m[:, 2]) & (y < m[:, 3])
        along = torch.where(m[:, 4] == 0, x - m[:, 0], y - m[:, 2])
        phase = along - torch.floor(along / m[:, 5]) * m[:, 5]
        painted = inside & ((m[:, 4] < 0) | (phase < m[:, 6]))
        paint = torch.where(painted, m[:, 7], torch.zeros_like(m[:, 7])).amax(-1)
        return paint.long()


class _Canvas:
    """Paints axis-aligned rectangles into a ground raster."""

    def __init__(self, x_range: tuple[float, float], y_range: tuple[float, float]) -> None:
        self.x0, self.y0 = x_range[0], y_range[0]
        nx = int(math.ceil((x_range[1] - x_range[0]) / _RASTER_RES))
        ny = int(math.ceil((y_range[1] - y_range[0]) / _RASTER_RES))
        self.classes = torch.full((nx, ny), TERRAIN, dtype=torch.uint8)
        self.markings: list[list[float]] = []

    def fill(self, x0: float, x1: float, y0: float, y1: float, label: int) -> None:
        nx, ny = self.classes.shape
        i0, i1 = (max(0, min(nx, round((v - self.x0) / _RASTER_RES))) for v in (x0, x1))
        j0, j1 = (max(0, min(ny, round((v - self.y0) / _RASTER_RES))) for v in (y0, y1))
        self.classes[i0:i1, j0:j1] = label

    def paint(
        self,
        x0: float,
        x1: float,
        y0: float,
        y1: float,
        dash_axis: int = -1,
        period: float = 1.0,
        on: float = 1.0,
        color: int = 1,
    ) -> None:
        self.markings.append([x0, x1, y0, y1, dash_axis, period, on, color])

    def finish(self) -> GroundMap:
        marks = torch.tensor(self.markings, dtype=torch.float32).reshape(-1, 8)
        return GroundMap(self.classes, (self.x0, self.y0), _RASTER_RES, marks)


# ----------------------------------------------------------------------------------------------
# Ego


@dataclass
class EgoPath:
    """The ego's path: straight from ``start`` along ``heading``, optionally a circular turn of
    ``turn`` radians (negative = right) with ``radius`` metres starting after ``turn_at`` metres,
    then straight again; driven at constant ``speed`` m/s from ``t = 0``."""

    start: tuple[float, float]
    heading: float
    speed: float
    turn_at: float = math.inf
    radius: float = 1.0
    turn: float = 0.0

    def pose(self, t: float) -> tuple[float, float, float]:
        """``(x, y, yaw)`` in the world frame at time ``t`` seconds (float64 maths)."""
        s = self.speed * t
        x0, y0 = self.start
        h = self.heading
        if s <= self.turn_at:
            return x0 + s * math.cos(h), y0 + s * math.sin(h), h
        x1, y1 = x0 + self.turn_at * math.cos(h), y0 + self.turn_at * math.sin(h)
        side = math.copysign(1.0, self.turn)
        cx, cy = x1 - side * self.radius * math.sin(h), y1 + side * self.radius * math.cos(h)
        arc = min(s - self.turn_at, self.radius * abs(self.turn))
        phi = side * arc / self.radius
        rx, ry = x1 - cx, y1 - cy
        x = cx + rx * math.cos(phi) - ry * math.sin(phi)
        y = cy + rx * math.sin(phi) + ry * math.cos(phi)
        rest = s - self.turn_at - arc
        yaw = h + phi
        return x + rest * math.cos(yaw), y + rest * math.sin(yaw), yaw


# ----------------------------------------------------------------------------------------------
# Agents


@dataclass
class Agents:
    """``A`` agents moving at constant velocity, each built from solids (its *parts*).

    Attributes:
        label: ``(A,)`` int64 Occ3D class.
        track_id: ``(A,)`` int64, stable over the scene.
        size: ``(A, 3)`` float32 box length (along heading), width, height, metres.
        start: ``(A, 2)`` float64 footprint centre at ``t = 0``, world frame.
        heading: ``(A,)`` float64 yaw, radians.
        speed: ``(A,)`` float64 m/s along the heading (0 = parked / standing).
        parts: solids in the agent's own frame (origin at the footprint centre on the ground,
            x along the heading); ``parts.instance`` is the owning agent's row.
    """

    label: Tensor
    track_id: Tensor
    size: Tensor
    start: Tensor
    heading: Tensor
    speed: Tensor
    parts: Primitives

    def __len__(self) -> int:
        return int(self.label.shape[0])

    def velocity(self) -> Tensor:
        """``(A, 2)`` float64 world-frame velocity, m/s."""
        return self.speed[:, None] * torch.stack([self.heading.cos(), self.heading.sin()], -1)

    def position(self, t: float) -> Tensor:
        """``(A, 2)`` float64 footprint centres at time ``t``."""
        return self.start + self.velocity() * t

    def parts_at(self, t: float) -> Primitives:
        """The parts placed in the world frame at time ``t`` (``instance`` = track id)."""
        owner = self.parts.instance
        pos, yaw = self.position(t)[owner], self.heading[owner]
        c, s = yaw.cos(), yaw.sin()
        local = self.parts.center.to(torch.float64)
        center = torch.stack(
            [pos[:, 0] + c * local[:, 0] - s * local[:, 1], pos[:, 1] + s * local[:, 0] + c * local[:, 1], local[:, 2]],
            -1,
        )
        out = self.parts.select(slice(None))
        out.center = center.to(torch.float32)
        out.yaw = (self.parts.yaw.to(torch.float64) + yaw).to(torch.float32)
        out.instance = self.track_id[owner]
        return out


# ----------------------------------------------------------------------------------------------
# Scene


@dataclass
class Scene:
    """One generated scene (see the module docstring for its frames).

    Attributes:
        name: scene name, e.g. ``"synth-train-0003"``.
        seed: the scene's own seed (also seeds per-frame sensor noise).
        ground: the ground map.
        static: static solids, world frame.
        agents: the moving (or parked) agents.
        ego: the ego's path.
        sun: ``(3,)`` float32 unit vector towards the sun, world frame.
        world_to_global: ``(4, 4)`` float64.
    """

    name: str
    seed: int
    ground: GroundMap
    static: Primitives
    agents: Agents
    ego: EgoPath
    sun: Tensor
    world_to_global: Tensor

    def ego_to_world(self, t: float) -> Tensor:
        """``(4, 4)`` float64 ego -> world pose at time ``t`` (ego origin on the ground)."""
        x, y, yaw = self.ego.pose(t)
        pose = torch.eye(4, dtype=torch.float64)
        pose[0, 0], pose[0, 1], pose[1, 0], pose[1, 1] = math.cos(yaw), -math.sin(yaw), math.sin(yaw), math.cos(yaw)
        pose[0, 3], pose[1, 3] = x, y
        return pose

    def primitives_at(self, t: float) -> Primitives:
        """Every solid at time ``t``, world frame."""
        return Primitives.cat([self.static, self.agents.parts_at(t)])


# ----------------------------------------------------------------------------------------------
# Generation

_BUILDING_COLORS = [
    (0.72, 0.62, 0.5),
    (0.6, 0.3, 0.22),
    (0.62, 0.62, 0.62),
    (0.82, 0.8, 0.74),
    (0.5, 0.42, 0.36),
    (0.55, 0.6, 0.66),
    (0.7, 0.55, 0.45),
]
_CAR_COLORS = [
    (0.85, 0.85, 0.85),
    (0.08, 0.08, 0.09),
    (0.6, 0.61, 0.63),
    (0.38, 0.39, 0.41),
    (0.6, 0.08, 0.08),
    (0.12, 0.22, 0.55),
    (0.12, 0.3, 0.18),
    (0.7, 0.63, 0.5),
    (0.85, 0.7, 0.1),
]
_BUS_COLORS = [(0.75, 0.12, 0.1), (0.15, 0.3, 0.65), (0.88, 0.88, 0.86), (0.9, 0.72, 0.1)]
_CLOTH_COLORS = [
    (0.1, 0.1, 0.12),
    (0.2, 0.25, 0.45),
    (0.6, 0.1, 0.12),
    (0.75, 0.75, 0.72),
    (0.35, 0.3, 0.25),
    (0.15, 0.4, 0.25),
    (0.8, 0.55, 0.2),
]
_SKIN_COLORS = [(0.87, 0.7, 0.58), (0.7, 0.52, 0.4), (0.45, 0.32, 0.24), (0.95, 0.8, 0.68)]

_SIZES = {  # (length, width, height) ranges
    CAR: ((3.9, 4.9), (1.75, 2.0), (1.45, 1.75)),
    TRUCK: ((6.0, 9.0), (2.3, 2.5), (2.8, 3.6)),
    BUS: ((10.0, 12.5), (2.5, 2.6), (3.0, 3.4)),
    TRAILER: ((7.0, 11.0), (2.4, 2.55), (3.2, 3.8)),
    CONSTRUCTION: ((5.0, 7.0), (2.4, 2.9), (2.8, 3.4)),
    MOTORCYCLE: ((1.9, 2.2), (0.7, 0.9), (1.4, 1.6)),
    BICYCLE: ((1.6, 1.8), (0.55, 0.7), (1.6, 1.8)),
    PEDESTRIAN: ((0.5, 0.7), (0.55, 0.75), (1.55, 1.9)),
}
_TRAFFIC_MIX = ((CAR, 0.72), (TRUCK, 0.09), (BUS, 0.06), (MOTORCYCLE, 0.07), (TRAILER, 0.03), (CONSTRUCTION, 0.03))
_PARKED_MIX = ((CAR, 0.86), (TRUCK, 0.05), (TRAILER, 0.04), (CONSTRUCTION, 0.05))


def _box(center, half, label, material, color, yaw=0.0) -> dict:
    return {
        "shape": BOX,
        "center": center,
        "half": half,
        "yaw": yaw,
        "label": label,
        "material": material,
        "color": color,
    }


def _cyl(center, radius, half_height, label, material, color, yaw=0.0) -> dict:
    return {
        "shape": CYLINDER,
        "center": center,
        "half": (radius, radius, half_height),
        "yaw": yaw,
        "label": label,
        "material": material,
        "color": color,
    }


def _ball(center, radius, half_height, label, material, color) -> dict:
    return {
        "shape": SPHEROID,
        "center": center,
        "half": (radius, radius, half_height),
        "yaw": 0.0,
        "label": label,
        "material": material,
        "color": color,
    }


def _agent_parts(label: int, length: float, width: float, height: float, color, rng: np.random.Generator) -> list[dict]:
    """Solids of one agent in its own frame (x forward, origin on the ground at the footprint centre)."""
    L, W, H = length, width, height  # noqa: N806 (vehicle dimensions read best as capitals)
    tyre = (0.07, 0.07, 0.07)
    if label == CAR:
        body_top = 0.55 * H
        return [
            _box((0, 0, 0.15), (0.44 * L, 0.47 * W, 0.15), label, M["tyre"], tyre),
            _box((0, 0, (0.3 + body_top) / 2), (L / 2, W / 2, (body_top - 0.3) / 2), label, M["paint"], color),
            _box((-0.06 * L, 0, (body_top + H) / 2), (0.3 * L, 0.46 * W, (H - body_top) / 2), label, M["glass"], color),
        ]
    if label == TRUCK:
        cargo = _pick(rng, _BUILDING_COLORS[2:4] + _CAR_COLORS[:1] + _BUS_COLORS)
        cab_top = 0.88 * H
        return [
            _box((0, 0, 0.25), (0.46 * L, 0.46 * W, 0.25), label, M["tyre"], tyre),
            _box((L / 2 - 1.1, 0, (0.5 + cab_top) / 2), (1.1, W / 2, (cab_top - 0.5) / 2), label, M["cab"], color),
            _box((-1.2, 0, (0.5 + H) / 2), ((L - 2.4) / 2, W / 2, (H - 0.5) / 2), label, M["cargo"], cargo),
        ]
    if label == BUS:
        return [
            _box((0, 0, 0.2), (0.46 * L, 0.47 * W, 0.2), label, M["tyre"], tyre),
            _box((0, 0, (0.4 + H) / 2), (L / 2, W / 2, (H - 0.4) / 2), label, M["bus"], color),
        ]
    if label == TRAILER:
        return [
            _box((0, 0, 0.3), (0.4 * L, 0.45 * W, 0.3), label, M["tyre"], tyre),
            _box((0, 0, (0.9 + H) / 2), (L / 2, W / 2, (H - 0.9) / 2), label, M["cargo"], color),
        ]
    if label == CONSTRUCTION:
        top = 0.62 * H
        return [
            _box((0, 0, 0.45), (0.45 * L, W / 2, 0.45), label, M["tyre"], (0.12, 0.12, 0.1)),
            _box((0, 0, (0.9 + top) / 2), (0.48 * L, 0.48 * W, (top - 0.9) / 2), label, M["paint"], color),
            _box((-0.15 * L, 0, (top + H) / 2), (0.22 * L, 0.4 * W, (H - top) / 2), label, M["cab"], color),
        ]
    cloth = _pick(rng, _CLOTH_COLORS)
    skin = _pick(rng, _SKIN_COLORS)
    if label == PEDESTRIAN:
        head = 0.115
        return [
            _cyl((0, 0, (H - 2 * head) / 2), 0.2, (H - 2 * head) / 2, label, M["cloth"], cloth),
            _ball((0, 0, H - head), head, head, label, M["skin"], skin),
        ]
    seat = 0.95
    rider = [
        _cyl((-0.08 * L, 0, (seat + H - 0.26) / 2), 0.2, (H - 0.26 - seat) / 2, label, M["cloth"], cloth),
        _ball((-0.05 * L, 0, H - 0.13), 0.13, 0.13, label, M["skin"], skin),
    ]
    if label == MOTORCYCLE:
        return [
            _box((0, 0, 0.32), (0.47 * L, 0.08, 0.32), label, M["tyre"], tyre),
            _box((0, 0, 0.75), (0.36 * L, 0.22, 0.2), label, M["paint"], color),
            *rider,
        ]
    return [_box((0, 0, 0.48), (L / 2, 0.05, 0.48), label, M["metal"], color), *rider]  # bicycle


def _pick(rng: np.random.Generator, options: list, jitter: float = 0.04) -> tuple[float, float, float]:
    base = np.asarray(options[int(rng.integers(len(options)))], dtype=np.float64)
    return tuple(float(v) for v in np.clip(base + rng.uniform(-jitter, jitter, 3), 0, 1))


def _mix(rng: np.random.Generator, mix: tuple) -> int:
    labels, weights = zip(*mix, strict=True)
    return int(rng.choice(labels, p=np.asarray(weights) / sum(weights)))


@dataclass
class _Road:
    """The cross-section of the main road (metres from its centre line) and the cross road."""

    lanes: int
    lane_width: float
    bike: float
    parking: dict[int, float]  # side (-1 right, +1 left) -> parking strip width
    sidewalk: float
    verge: float
    cross_x: float | None
    cross_lane: float
    cross_sidewalk: float

    def curb(self, side: int) -> float:
        return self.lanes * self.lane_width + self.bike + self.parking[side]

    def frontage(self, side: int) -> float:
        return self.curb(side) + self.sidewalk + self.verge

    def corridor(self) -> tuple[float, float]:
        """x interval taken by the cross road and its sidewalks (empty without a cross road)."""
        if self.cross_x is None:
            return (math.inf, -math.inf)
        half = self.cross_lane + self.cross_sidewalk
        return (self.cross_x - half, self.cross_x + half)


class _SceneBuilder:
    """Accumulates solids, agents and ground paint for one scene."""

    def __init__(self, config: SyntheticWorldConfig, rng: np.random.Generator, duration: float) -> None:
        self.config, self.rng, self.duration = config, rng, duration
        self.static: list[dict] = []
        self.agent_rows: list[dict] = []
        self.parts: list[dict] = []

    # -- agents ---------------------------------------------------------------------------------

    def agent(self, label: int, xy: tuple[float, float], heading: float, speed: float, color=None) -> None:
        rng = self.rng
        (l0, l1), (w0, w1), (h0, h1) = _SIZES[label]
        size = (rng.uniform(l0, l1), rng.uniform(w0, w1), rng.uniform(h0, h1))
        if color is None:
            palette = {
                BUS: _BUS_COLORS,
                CONSTRUCTION: [(0.85, 0.65, 0.1)],
                TRAILER: _BUILDING_COLORS[2:4] + _CAR_COLORS[:1],
            }
            color = _pick(rng, palette.get(label, _CAR_COLORS))
        row = len(self.agent_rows)
        for part in _agent_parts(label, *size, color, rng):
            self.parts.append({**part, "instance": row})
        self.agent_rows.append({"label": label, "size": size, "start": xy, "heading": heading, "speed": speed})

    def sizes_hint(self, label: int) -> float:
        """Longest length of a class: spacing by it keeps neighbours from overlapping."""
        (_, l1), _, _ = _SIZES[label]
        return l1

    def fill_line(
        self, start: float, end: float, per_100m: float, min_gap: float, mix: tuple
    ) -> list[tuple[float, int]]:
        """Positions and classes along ``[start, end]`` with mean spacing ``100 / per_100m`` metres."""
        out: list[tuple[float, int]] = []
        if per_100m <= 0:
            return out
        pos = start + self.rng.uniform(0, 100 / per_100m)
        while pos < end:
            label = _mix(self.rng, mix)
            out.append((pos, label))
            pos += self.sizes_hint(label) + min_gap + self.rng.exponential(max(1e-3, 100 / per_100m - min_gap))
        return out

    # -- results --------------------------------------------------------------------------------

    def agents(self) -> Agents:
        rows = self.agent_rows
        n = len(rows)
        return Agents(
            label=torch.tensor([r["label"] for r in rows], dtype=torch.int64),
            track_id=torch.arange(n, dtype=torch.int64),
            size=torch.tensor([r["size"] for r in rows], dtype=torch.float32).reshape(n, 3),
            start=torch.tensor([r["start"] for r in rows], dtype=torch.float64).reshape(n, 2),
            heading=torch.tensor([r["heading"] for r in rows], dtype=torch.float64),
            speed=torch.tensor([r["speed"] for r in rows], dtype=torch.float64),
            parts=Primitives.from_rows(self.parts),
        )


def _road_profile(rng: np.random.Generator) -> _Road:
    return _Road(
        lanes=int(rng.choice([1, 2], p=[0.4, 0.6])),
        lane_width=float(rng.uniform(3.2, 3.6)),
        bike=1.5 if rng.random() < 0.5 else 0.0,
        parking={side: (2.4 if rng.random() < 0.7 else 0.0) for side in (-1, 1)},
        sidewalk=float(rng.uniform(2.5, 4.0)),
        verge=float(rng.uniform(1.2, 3.0)) if rng.random() < 0.6 else 0.0,
        cross_x=None,
        cross_lane=float(rng.uniform(3.0, 3.5)),
        cross_sidewalk=float(rng.uniform(2.2, 3.5)),
    )


def _ego_path(rng: np.random.Generator, road: _Road, duration: float) -> EgoPath:
    """The ego's path; also decides where (and whether) the cross road is."""
    has_cross = rng.random() < 0.7
    turning = has_cross and rng.random() < 0.35
    if turning:
        lane = road.lanes - 1
        speed = float(rng.uniform(3.5, 6.0))
    else:
        lane = int(rng.integers(road.lanes))
        speed = float(rng.uniform(4.0, 9.0))
    y = -(lane + 0.5) * road.lane_width
    travel = speed * duration
    if turning:
        # A right turn from the lane into the cross road's outgoing lane (heading -y at x_c - w/2):
        # radius = lane-to-curb offset + half a cross lane keeps the arc on the road at both curbs.
        radius = road.curb(-1) - abs(y) + road.cross_lane / 2
        turn_at = float(rng.uniform(0.15, 0.5)) * travel
        road.cross_x = turn_at + radius + road.cross_lane / 2
        return EgoPath((0.0, y), 0.0, speed, turn_at, radius, -math.pi / 2)
    if has_cross:
        road.cross_x = float(rng.uniform(0.1, 0.9)) * travel + float(rng.uniform(-15, 15))
    return EgoPath((0.0, y), 0.0, speed)


def _paint_roads(canvas: _Canvas, road: _Road, x_range: tuple[float, float], y_range: tuple[float, float]) -> None:
    xa, xb = x_range
    ya, yb = y_range
    white, yellow = 1, 2
    for side in (-1, 1):  # main-road sidewalks
        c, s = road.curb(side), road.sidewalk
        canvas.fill(xa, xb, *sorted((side * c, side * (c + s))), SIDEWALK)
    cx = road.cross_x
    if cx is not None:
        w, s = road.cross_lane, road.cross_sidewalk
        canvas.fill(cx - w - s, cx - w, ya, yb, SIDEWALK)
        canvas.fill(cx + w, cx + w + s, ya, yb, SIDEWALK)
    canvas.fill(xa, xb, -road.curb(-1), road.curb(1), ROAD)
    if cx is not None:
        canvas.fill(cx - road.cross_lane, cx + road.cross_lane, ya, yb, ROAD)
    # markings on the main road, interrupted by the intersection
    ca, cb = road.corridor()
    spans = [(xa, xb)] if cx is None else [(xa, ca), (cb, xb)]
    n, lw = road.lanes, road.lane_width
    for x0, x1 in spans:
        if x1 <= x0:
            continue
        canvas.paint(x0, x1, 0.08, 0.2, color=yellow)
        canvas.paint(x0, x1, -0.2, -0.08, color=yellow)
        for side in (-1, 1):
            for k in range(1, n):
                canvas.paint(x0, x1, *sorted((side * (k * lw - 0.06), side * (k * lw + 0.06))), 0, 9.0, 3.0, white)
            edge = n * lw
            canvas.paint(x0, x1, *sorted((side * (edge - 0.07), side * (edge + 0.07))), color=white)
            if road.bike and road.parking[side]:
                b = edge + road.bike
                canvas.paint(x0, x1, *sorted((side * (b - 0.06), side * (b + 0.06))), color=white)
    if cx is None:
        return
    w = road.cross_lane
    for side in (-1, 1):
        c, s = road.curb(side), road.sidewalk
        # zebra crossing where the main sidewalk crosses the cross road; bars run along the traffic
        canvas.paint(cx - w, cx + w, *sorted((side * (c + 0.3), side * (c + s - 0.3))), 0, 1.0, 0.5, white)
        # the cross road's centre line and stop line (incoming lane: x > x_c on the right side)
        y0, y1 = sorted((side * (c + s), side * (yb if side > 0 else -ya)))
        canvas.paint(cx - 0.06, cx + 0.06, y0, y1, 1, 6.0, 3.0, white)
        stop = side * (c + s + 0.6)
        lane_x = (cx, cx + w) if side < 0 else (cx - w, cx)
        canvas.paint(lane_x[0], lane_x[1], stop - 0.2, stop + 0.2, color=white)


def _add_lots(b: _SceneBuilder, canvas: _Canvas, origin, along, outward, length: float) -> None:
    """Buildings, parking lots and green lots along a frontage line ``origin + along * a``."""
    rng, density = b.rng, b.config.structure_density
    ox, oy = origin
    ax, ay = along
    nx, ny = outward
    yaw = math.atan2(ay, ax)

    def at(a: float, d: float) -> tuple[float, float]:
        return ox + ax * a + nx * d, oy + ay * a + ny * d

    a = float(rng.uniform(0, 6))
    while a < length - 4:
        lot = min(float(rng.uniform(10, 28)), length - a)
        kind = rng.choice(3, p=[0.58, 0.14, 0.28])
        if kind == 0:  # building
            gap = float(rng.uniform(1.0, 5.0))
            setback, depth, height = float(rng.uniform(0.5, 4.0)), float(rng.uniform(8, 16)), float(rng.uniform(4, 16))
            cx, cy = at(a + lot / 2, setback + depth / 2)
            b.static.append(
                _box(
                    (cx, cy, height / 2),
                    ((lot - gap) / 2, depth / 2, height / 2),
                    MANMADE,
                    M["building"],
                    _pick(rng, _BUILDING_COLORS),
                    yaw,
                )
            )
        elif kind == 1:  # parking lot: gravel, a back wall, cars parked nose-in
            corners = [at(a, 0), at(a + lot, 16)]
            xs, ys = sorted(c[0] for c in corners), sorted(c[1] for c in corners)
            canvas.fill(xs[0], xs[1], ys[0], ys[1], OTHER_FLAT)
            wx, wy = at(a + lot / 2, 15.5)
            b.static.append(_box((wx, wy, 0.7), (lot / 2, 0.15, 0.7), MANMADE, M["concrete"], (0.6, 0.6, 0.58), yaw))
            slot = 2.8
            for k in range(int((lot - 1) // slot)):
                if rng.random() < 0.55:
                    px, py = at(a + 1 + (k + 0.5) * slot, 8.0)
                    nose = math.atan2(ny, nx) + math.pi * (rng.random() < 0.5)  # nose in or out
                    b.agent(CAR, (px, py), nose + float(rng.uniform(-0.05, 0.05)), 0.0)
        else:  # green: trees and a hedge
            for _ in range(int(rng.integers(1, 4) * density + 0.5)):
                _tree(b, at(a + float(rng.uniform(2, max(2.5, lot - 2))), float(rng.uniform(3, 12))))
            if rng.random() < 0.5 * density:
                hx, hy = at(a + lot / 2, 0.8)
                h = float(rng.uniform(0.8, 1.5))
                b.static.append(
                    _box(
                        (hx, hy, h / 2),
                        ((lot - 2) / 2, 0.5, h / 2),
                        VEGETATION,
                        M["hedge"],
                        _pick(rng, [(0.12, 0.28, 0.1)]),
                        yaw,
                    )
                )
        a += lot


def _tree(b: _SceneBuilder, xy: tuple[float, float]) -> None:
    rng = b.rng
    trunk_h, trunk_r = float(rng.uniform(2.8, 4.0)), float(rng.uniform(0.15, 0.3))
    crown_r, crown_h = float(rng.uniform(1.4, 2.6)), float(rng.uniform(1.2, 2.0))
    bark = _pick(rng, [(0.35, 0.25, 0.16)])
    b.static.append(_cyl((xy[0], xy[1], trunk_h / 2), trunk_r, trunk_h / 2, VEGETATION, M["bark"], bark))
    b.static.append(
        _ball(
            (xy[0], xy[1], trunk_h + 0.7 * crown_h),
            crown_r,
            crown_h,
            VEGETATION,
            M["crown"],
            _pick(rng, [(0.22, 0.42, 0.14), (0.3, 0.45, 0.18), (0.18, 0.35, 0.16)]),
        )
    )


def _add_street_furniture(
    b: _SceneBuilder, road: _Road, x_range: tuple[float, float]
) -> list[tuple[int, float, float]]:
    """Trees and hedges on the verges, street lights, a road-works zone; returns the zones
    ``(side, x0, x1)`` kept free of parked cars."""
    rng, density = b.rng, b.config.structure_density
    xa, xb = x_range
    ca, cb = road.corridor()
    free = lambda x, pad: not (ca - pad <= x <= cb + pad)  # noqa: E731
    for side in (-1, 1):
        if road.verge >= 1.0 and density > 0:
            y = side * (road.curb(side) + road.sidewalk + road.verge / 2)
            x = xa + float(rng.uniform(0, 8))
            while x < xb:
                if free(x, 3):
                    if rng.random() < 0.8:
                        _tree(b, (x, y))
                    else:
                        length = float(rng.uniform(3, 8))
                        h = float(rng.uniform(0.8, 1.4))
                        b.static.append(
                            _box(
                                (x, y, h / 2),
                                (length / 2, min(0.5, road.verge / 2 - 0.1), h / 2),
                                VEGETATION,
                                M["hedge"],
                                _pick(rng, [(0.12, 0.28, 0.1)]),
                            )
                        )
                x += float(rng.uniform(7, 14)) / density
        if density > 0:
            y = side * (road.curb(side) + 0.35)
            x = xa + float(rng.uniform(0, 20))
            while x < xb:
                if free(x, 1):
                    h = float(rng.uniform(5, 8))
                    b.static.append(_cyl((x, y, h / 2), 0.12, h / 2, MANMADE, M["metal"], (0.45, 0.47, 0.5)))
                x += float(rng.uniform(25, 35)) / density
    zones = []
    for _ in range(int(rng.poisson(0.8 * density))):
        side = int(rng.choice([-1, 1]))
        length = float(rng.uniform(8, 16))
        x0 = float(rng.uniform(xa + 10, xb - 10 - length))
        if not (free(x0, 4) and free(x0 + length, 4)):
            continue
        zones.append((side, x0, x0 + length))
        # barriers on the parking strip (or the sidewalk edge without one), cones tapering in front
        y = side * (road.curb(side) - road.parking[side] / 2) if road.parking[side] else side * (road.curb(side) + 0.5)
        jersey = rng.random() < 0.5
        x = x0
        while x + 2.0 <= x0 + length:
            color = (0.62, 0.62, 0.6) if jersey else (0.9, 0.9, 0.88)
            material = M["concrete"] if jersey else M["barrier"]
            b.static.append(_box((x + 1.0, y, 0.45), (1.0, 0.25, 0.45), BARRIER, material, color))
            x += 2.05
        lead = -1 if side < 0 else 1  # cones on the approach side of the traffic next to it
        for k in range(int(rng.integers(2, 6))):
            cx = (x0 - 1.5 - 1.8 * k) if lead < 0 else (x0 + length + 1.5 + 1.8 * k)
            cy = y - side * 0.35 * k * (road.parking[side] > 0)
            b.static.append(_cyl((cx, cy, 0.375), 0.18, 0.375, CONE, M["cone"], (0.95, 0.35, 0.05)))
    return zones


def _add_traffic(
    b: _SceneBuilder,
    road: _Road,
    ego: EgoPath,
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    zones: list[tuple[int, float, float]],
    turning: bool,
) -> None:
    cfg, rng, duration = b.config, b.rng, b.duration
    xa, xb = x_range
    ya, yb = y_range
    n, lw = road.lanes, road.lane_width
    ego_lane_y = ego.start[1]
    ca, cb = road.corridor()
    # moving vehicles: one speed per lane keeps a lane collision-free
    for side in (-1, 1):
        heading = 0.0 if side < 0 else math.pi
        for k in range(n):
            y = side * (k + 0.5) * lw
            mine = side < 0 and abs(y - ego_lane_y) < 1e-6
            speed = ego.speed if mine else float(rng.uniform(3.0, 11.0))
            span = speed * duration + 20
            lo, hi = (xa - span, xb + 20) if side < 0 else (xa - 20, xb + span)
            ahead, behind = _ego_lane_speeds(rng, ego.speed, cfg.ego_lane_speed_offset) if mine else (speed, speed)
            for x, label in b.fill_line(lo, hi, cfg.vehicle_density, 4.0, _TRAFFIC_MIX):
                if mine and abs(x - ego.start[0]) < b.sizes_hint(label) / 2 + 9.0:
                    continue  # keep the ego's own slot free
                b.agent(label, (x, y), heading, ahead if x > ego.start[0] else behind)
        if road.bike and cfg.cyclist_density > 0:
            y = side * (n * lw + road.bike / 2)
            speed = float(rng.uniform(3.0, 6.0))
            span = speed * duration + 10
            lo, hi = (xa - span, xb) if side < 0 else (xa, xb + span)
            for x, _ in b.fill_line(lo, hi, cfg.cyclist_density, 3.0, ((BICYCLE, 1.0),)):
                b.agent(BICYCLE, (x, y), heading, speed)
        if road.parking[side] and cfg.parked_density > 0:
            y = side * (road.curb(side) - road.parking[side] / 2)
            for x, label in b.fill_line(xa, xb, cfg.parked_density, 1.0, _PARKED_MIX):
                blocked = any(s == side and z0 - 5 < x < z1 + 5 for s, z0, z1 in zones) or ca - 6 < x < cb + 6
                if not blocked:
                    b.agent(label, (x, y), heading + float(rng.uniform(-0.03, 0.03)), 0.0)
    # the cross road: a queue waiting at each stop line, traffic leaving the intersection
    if road.cross_x is not None:
        cx, w = road.cross_x, road.cross_lane
        for side in (-1, 1):
            edge = road.curb(side) + road.sidewalk
            inbound_x, outbound_x = (cx + w / 2, cx - w / 2) if side < 0 else (cx - w / 2, cx + w / 2)
            toward, away = (math.pi / 2, -math.pi / 2) if side < 0 else (-math.pi / 2, math.pi / 2)
            far = -ya if side < 0 else yb
            queue = edge + 1.2
            for _ in range(int(rng.integers(0, 4))):
                label = _mix(rng, _TRAFFIC_MIX[:3])
                half = b.sizes_hint(label) / 2 + 0.6
                b.agent(label, (inbound_x, side * (queue + half)), toward, 0.0)
                queue += 2 * half + float(rng.uniform(1.0, 2.5))
            if not (turning and side < 0):  # that lane is the ego's way out
                speed = float(rng.uniform(4.0, 10.0))
                for d, label in b.fill_line(
                    edge + 8, far + speed * duration, cfg.vehicle_density, 4.0, _TRAFFIC_MIX[:3]
                ):
                    b.agent(label, (outbound_x, side * d), away, speed)
    # pedestrians: along the main sidewalks (crossing the cross road on its zebra crossings) ...
    if cfg.pedestrian_density <= 0:
        return
    for side in (-1, 1):
        c, s = road.curb(side), road.sidewalk
        count = int(rng.poisson(cfg.pedestrian_density * (xb - xa) / 100))
        for _ in range(count):
            x = float(rng.uniform(xa, xb))
            speed = 0.0 if rng.random() < 0.2 else float(rng.uniform(0.8, 1.6))
            heading = 0.0 if rng.random() < 0.5 else math.pi
            if turning and side < 0:  # keep the ego's turn across this crossing clear
                x_end = x + math.cos(heading) * speed * duration
                if min(x, x_end) < cb + 1.5 and max(x, x_end) > ca - 1.5:
                    continue
            b.agent(PEDESTRIAN, (x, side * (c + float(rng.uniform(0.8, max(0.9, s - 0.5))))), heading, speed)
    # ... and along the cross road's sidewalks, walking away from the main road
    if road.cross_x is None:
        return
    for side in (-1, 1):
        start = road.frontage(side) + 2
        far = -ya if side < 0 else yb
        for xside in (-1, 1):
            count = int(rng.poisson(cfg.pedestrian_density * max(0.0, far - start) / 200))
            for _ in range(count):
                d = float(rng.uniform(start, far))
                x = road.cross_x + xside * (
                    road.cross_lane + float(rng.uniform(0.6, max(0.7, road.cross_sidewalk - 0.5)))
                )
                b.agent(PEDESTRIAN, (x, side * d), side * math.pi / 2, float(rng.uniform(0.8, 1.5)))


def _ego_lane_speeds(rng: np.random.Generator, ego_speed: float, offset: tuple[float, float]) -> tuple[float, float]:
    """Speeds of the ego lane's traffic ahead of and behind the ego: ``ego_speed +- d`` with one
    ``d ~ U(offset)`` per scene (faster ahead, slower behind: nobody in the lane ever meets the ego
    or another car); ``offset == (0, 0)`` draws nothing and gives the ego's speed to both."""
    if offset[0] == 0 and offset[1] == 0:
        return ego_speed, ego_speed
    d = float(rng.uniform(offset[0], offset[1]))
    return ego_speed + d, max(0.0, ego_speed - d)


def _path_extent(ego: EgoPath, duration: float) -> tuple[float, float, float, float]:
    pts = [ego.pose(duration * k / 20)[:2] for k in range(21)]
    xs, ys = [p[0] for p in pts], [p[1] for p in pts]
    return min(xs), max(xs), min(ys), max(ys)


def build_scene(config: SyntheticWorldConfig, split: str, index: int) -> Scene:
    """Generate scene ``index`` of ``split`` (deterministic in ``(config, split, index)``)."""
    seq = np.random.SeedSequence([config.seed, SPLIT_IDS[split], index])
    seed = int(seq.generate_state(1)[0])
    rng = np.random.default_rng(seq)
    duration = (config.frames(split) - 1) / config.fps
    road = _road_profile(rng)
    ego = _ego_path(rng, road, duration)
    turning = math.isfinite(ego.turn_at)
    x0, x1, y0, y1 = _path_extent(ego, duration)
    margin = config.world_margin
    x_range = (x0 - margin, x1 + margin)
    y_range = (min(y0, 0.0) - margin, max(y1, 0.0) + margin)
    canvas = _Canvas(x_range, y_range)
    b = _SceneBuilder(config, rng, duration)
    _paint_roads(canvas, road, x_range, y_range)
    # lots along the main road (both sides, minus the cross road) and along the cross road
    ca, cb = road.corridor()
    for side in (-1, 1):
        f = road.frontage(side)
        spans = [(x_range[0], x_range[1])] if road.cross_x is None else [(x_range[0], ca - 1), (cb + 1, x_range[1])]
        for a0, a1 in spans:
            if a1 - a0 > 8:
                _add_lots(b, canvas, (a0, side * f), (1.0, 0.0), (0.0, float(side)), a1 - a0)
    if road.cross_x is not None:
        for side in (-1, 1):
            start = road.frontage(side) + 18  # beyond the main road's lots
            far = -y_range[0] if side < 0 else y_range[1]
            for xside in (-1, 1):
                x = road.cross_x + xside * (road.cross_lane + road.cross_sidewalk)
                if far - start > 8:
                    _add_lots(b, canvas, (x, side * start), (0.0, float(side)), (float(xside), 0.0), far - start)
    zones = _add_street_furniture(b, road, x_range)
    _add_traffic(b, road, ego, x_range, y_range, zones, turning)
    sun_az, sun_el = float(rng.uniform(-math.pi, math.pi)), math.radians(float(rng.uniform(25, 65)))
    sun = torch.tensor([math.cos(sun_el) * math.cos(sun_az), math.cos(sun_el) * math.sin(sun_az), math.sin(sun_el)])
    g_yaw = float(rng.uniform(-math.pi, math.pi))
    world_to_global = torch.eye(4, dtype=torch.float64)
    c, s = math.cos(g_yaw), math.sin(g_yaw)
    world_to_global[:2, :2] = torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    world_to_global[:2, 3] = torch.tensor(rng.uniform(-2000, 2000, 2), dtype=torch.float64)
    return Scene(
        name=f"synth-{split}-{index:04d}",
        seed=seed,
        ground=canvas.finish(),
        static=Primitives.from_rows(b.static),
        agents=b.agents(),
        ego=ego,
        sun=sun,
        world_to_global=world_to_global,
    )
