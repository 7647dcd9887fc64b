"""How surfaces look: procedural textures, sky and Lambertian shading.

Textures are functions of coordinates fixed to the surface (world coordinates for the ground, the
solid's local frame for solids), so a surface looks the same from every camera and in every frame.
Colours carry no depth code: they depend on the surface, its orientation to the sun, and texture
detail whose apparent scale shrinks with distance (perspective), which is what makes depth learnable.
"""

from __future__ import annotations

import torch
from torch import Tensor

from occplug.data.classes import OCC3D_CLASSES

__all__ = [
    "MATERIALS",
    "REFLECTIVITY",
    "ground_albedo",
    "lidar_reflectivity",
    "shade",
    "sky_color",
    "solid_albedo",
    "value_noise",
]

#: Material ids of solids (``Primitives.material``).
MATERIALS = {
    name: i
    for i, name in enumerate(
        (
            "building", "concrete", "crown", "bark", "hedge", "paint", "glass", "tyre", "cab", "cargo",
            "bus", "cloth", "skin", "barrier", "cone", "metal",
        )
    )
}
#: LiDAR reflectivity per Occ3D class id (index 17 = free is unused).
REFLECTIVITY = torch.tensor(
    [0.5, 0.7, 0.45, 0.6, 0.6, 0.55, 0.55, 0.35, 0.9, 0.55, 0.6, 0.25, 0.3, 0.35, 0.3, 0.45, 0.4, 0.0]
)
assert REFLECTIVITY.numel() == len(OCC3D_CLASSES)

_GLASS = torch.tensor([0.10, 0.13, 0.17])
_MARK_WHITE = torch.tensor([0.88, 0.88, 0.85])
_MARK_YELLOW = torch.tensor([0.85, 0.68, 0.18])


def _hash(cells: Tensor, seed: int) -> Tensor:
    """Uniform [0, 1) pseudo-random value per integer cell ``(..., D)`` int64 (deterministic)."""
    primes = (73856093, 19349663, 83492791)
    h = torch.full(cells.shape[:-1], seed * 2654435761 % (1 << 31), dtype=torch.int64, device=cells.device)
    for axis in range(cells.shape[-1]):
        h = h ^ (cells[..., axis] * primes[axis])
    h = (h ^ (h >> 13)) * 1274126177
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF).to(torch.float32) / float(1 << 24)


def value_noise(points: Tensor, scale: float, seed: int = 0) -> Tensor:
    """Smooth value noise in [0, 1] at ``(..., D)`` points (D = 2 or 3), feature size ``scale`` metres."""
    q = points.to(torch.float64) / scale
    base = torch.floor(q)
    f = (q - base).to(torch.float32)
    f = f * f * (3 - 2 * f)
    cells = base.to(torch.int64)
    dims = points.shape[-1]
    out = torch.zeros(points.shape[:-1], device=points.device)
    for corner in range(1 << dims):
        bits = [(corner >> a) & 1 for a in range(dims)]
        offset = torch.tensor(bits, device=points.device)
        weight = torch.ones_like(out)
        for a in range(dims):
            weight = weight * (f[..., a] if bits[a] else 1 - f[..., a])
        out = out + weight * _hash(cells + offset, seed)
    return out


def fbm(points: Tensor, scale: float, octaves: int = 3, seed: int = 0) -> Tensor:
    """Fractal sum of :func:`value_noise` octaves, normalised to [0, 1]."""
    total, amp, norm = torch.zeros(points.shape[:-1], device=points.device), 1.0, 0.0
    for octave in range(octaves):
        total = total + amp * value_noise(points, scale / 2**octave, seed + octave)
        norm += amp
        amp *= 0.5
    return total / norm


def _frac(x: Tensor) -> Tensor:
    return x - torch.floor(x)


def _asphalt(xy: Tensor) -> Tensor:
    tone = 0.22 + 0.09 * value_noise(xy, 0.35, seed=1) + 0.08 * value_noise(xy, 5.0, seed=2)
    return tone[:, None] * torch.tensor([1.0, 1.0, 1.04])


def _gravel(xy: Tensor) -> Tensor:
    tone = 0.33 + 0.12 * value_noise(xy, 0.12, seed=3) + 0.08 * value_noise(xy, 5.0, seed=2)
    return tone[:, None] * torch.tensor([1.15, 1.05, 0.9])


def _pavers(xy: Tensor) -> Tensor:
    tile = 0.55 + 0.1 * _hash(torch.floor(xy / 0.5).to(torch.int64), seed=4)
    grout = (_frac(xy[:, 0] / 0.5) < 0.06) | (_frac(xy[:, 1] / 0.5) < 0.06)
    tone = torch.where(grout, tile * 0.7, tile) + 0.05 * value_noise(xy, 0.35, seed=1)
    return tone[:, None] * torch.tensor([1.0, 0.98, 0.94])


def _grass(xy: Tensor) -> Tensor:
    coarse = value_noise(xy, 5.0, seed=2)
    blades = value_noise(xy, 0.15, seed=5)
    green = torch.stack([0.16 + 0.1 * coarse, 0.30 + 0.2 * blades, 0.10 + 0.04 * blades], -1)
    dirt = torch.tensor([0.36, 0.30, 0.2])
    patch = ((coarse - 0.62) * 6).clamp(0, 1)[:, None]
    return green * (1 - patch) + dirt * patch


_GROUND_TEXTURES = {11: _asphalt, 12: _gravel, 13: _pavers, 14: _grass}


def ground_albedo(labels: Tensor, xy: Tensor, marking: Tensor) -> Tensor:
    """Albedo ``(K, 3)`` of ground points.

    Args:
        labels: ``(K,)`` int64 ground class (11 road, 12 other_flat, 13 sidewalk, 14 terrain).
        xy: ``(K, 2)`` world coordinates, metres.
        marking: ``(K,)`` int64 paint (0 none, 1 white, 2 yellow), drawn over any class.
    """
    out = torch.empty(labels.shape[0], 3)
    for label, texture in _GROUND_TEXTURES.items():
        rows = labels == label
        if label == 14:
            rows = ~torch.isin(labels, torch.tensor([11, 12, 13]))  # anything else reads as terrain
        if rows.any():
            out[rows] = texture(xy[rows])
    for paint, color in ((1, _MARK_WHITE), (2, _MARK_YELLOW)):
        rows = marking == paint
        if rows.any():
            out[rows] = color * (0.92 + 0.08 * value_noise(xy[rows], 0.35, seed=1)[:, None])
    return out


# Solid textures: (color (K, 3), local (K, 3), half (K, 3), face_axis (K,)) -> albedo (K, 3).
# ``along`` is the horizontal coordinate running along a vertical face, ``height`` is above the
# solid's base.


def _along(local: Tensor, face_axis: Tensor) -> Tensor:
    return torch.where(face_axis == 0, local[:, 1], local[:, 0])


def _building(color: Tensor, local: Tensor, half: Tensor, face_axis: Tensor) -> Tensor:
    """Brick courses, a window grid on every 3 m floor, gravel roof."""
    height, along = local[:, 2] + half[:, 2], _along(local, face_axis)
    course = torch.floor(height / 0.25)
    brick_u = _frac((along + 0.3 * torch.remainder(course, 2)) / 0.6)
    mortar = (_frac(height / 0.25) < 0.12) | (brick_u < 0.06)
    brick_id = torch.stack([course.long(), torch.floor(along / 0.6).long()], -1)
    wall = color * torch.where(mortar, 1.18, 0.9 + 0.2 * _hash(brick_id, 8))[:, None]
    floor, bay = _frac(height / 3.0), _frac(along / 2.6)
    window = (floor > 0.33) & (floor < 0.78) & (bay > 0.22) & (bay < 0.78) & (height > 0.9)
    glass = _GLASS + 0.08 * value_noise(torch.stack([along, height], -1), 1.5, seed=9)[:, None]
    roof = torch.tensor([0.3, 0.3, 0.32]) * (0.8 + 0.4 * value_noise(local, 0.3, seed=7)[:, None])
    return torch.where((face_axis == 2)[:, None], roof, torch.where(window[:, None], glass, wall))


def _modulated(scale: float, seed: int, low: float, gain: float):  # noqa: ANN202 (texture factory)
    def texture(color: Tensor, local: Tensor, half: Tensor, face_axis: Tensor) -> Tensor:
        return color * (low + gain * value_noise(local, scale, seed))[:, None]

    return texture


def _bark(color: Tensor, local: Tensor, half: Tensor, face_axis: Tensor) -> Tensor:
    uv = torch.stack([torch.atan2(local[:, 1], local[:, 0]) * 0.25, (local[:, 2] + half[:, 2]) / 0.6], -1)
    return color * (0.7 + 0.5 * value_noise(uv, 0.12, seed=12))[:, None]


def _crown(color: Tensor, local: Tensor, half: Tensor, face_axis: Tensor) -> Tensor:
    leaf = value_noise(local, 0.18, seed=11)
    clumps = value_noise(local, 0.6, seed=7)
    return color * (0.55 + 0.8 * leaf * (0.6 + 0.4 * clumps))[:, None]


def _glass(color: Tensor, local: Tensor, half: Tensor, face_axis: Tensor) -> Tensor:
    return _GLASS + 0.25 * color


def _tyre(color: Tensor, local: Tensor, half: Tensor, face_axis: Tensor) -> Tensor:
    return torch.full_like(color, 0.07)


def _banded(low: float, high: float):  # noqa: ANN202 (texture factory)
    """Paint with a glass band on the sides between fractions ``low`` and ``high`` of the height."""

    def texture(color: Tensor, local: Tensor, half: Tensor, face_axis: Tensor) -> Tensor:
        frac = (local[:, 2] + half[:, 2]) / (2 * half[:, 2])
        band = (face_axis != 2) & (frac > low) & (frac < high)
        return torch.where(band[:, None], _GLASS.expand_as(color), color)

    return texture


def _cargo(color: Tensor, local: Tensor, half: Tensor, face_axis: Tensor) -> Tensor:
    ribs = _frac(_along(local, face_axis) / 0.45) < 0.1
    return color * torch.where(ribs, 0.8, 1.0)[:, None]


def _barrier(color: Tensor, local: Tensor, half: Tensor, face_axis: Tensor) -> Tensor:
    stripe = _frac((_along(local, face_axis) + local[:, 2] + half[:, 2]) / 1.0) < 0.5
    return torch.where(stripe[:, None], torch.tensor([0.8, 0.12, 0.1]), torch.tensor([0.9, 0.9, 0.88]))


def _cone(color: Tensor, local: Tensor, half: Tensor, face_axis: Tensor) -> Tensor:
    frac = (local[:, 2] + half[:, 2]) / (2 * half[:, 2])
    band = (frac > 0.45) & (frac < 0.65)
    return torch.where(band[:, None], torch.tensor([0.92, 0.92, 0.92]), color)


_SOLID_TEXTURES = {
    "building": _building,
    "concrete": _modulated(0.2, 10, 0.85, 0.3),
    "crown": _crown,
    "bark": _bark,
    "hedge": _modulated(0.12, 13, 0.6, 0.7),
    "paint": _modulated(0.3, 7, 0.95, 0.1),
    "glass": _glass,
    "tyre": _tyre,
    "cab": _banded(0.6, 1.01),
    "cargo": _cargo,
    "bus": _banded(0.38, 0.8),
    "cloth": _modulated(0.08, 14, 0.85, 0.3),
    "skin": lambda color, *_: color,
    "barrier": _barrier,
    "cone": _cone,
    "metal": _modulated(0.3, 7, 0.9, 0.2),
}
assert set(_SOLID_TEXTURES) == set(MATERIALS)


def solid_albedo(material: Tensor, color: Tensor, local: Tensor, half: Tensor, face_axis: Tensor) -> Tensor:
    """Albedo ``(K, 3)`` of points on solids.

    Args:
        material: ``(K,)`` material id (:data:`MATERIALS`).
        color: ``(K, 3)`` the solid's base colour.
        local: ``(K, 3)`` hit points in the solid's local frame (centred, heading-aligned), metres.
        half: ``(K, 3)`` the solid's half-extents.
        face_axis: ``(K,)`` local axis of the face normal (0: x, 1: y, 2: top/bottom).
    """
    out = color.clone()
    for name, texture in _SOLID_TEXTURES.items():
        rows = material == MATERIALS[name]
        if rows.any():
            out[rows] = texture(color[rows], local[rows], half[rows], face_axis[rows])
    return out.clamp(0, 1)


def sky_color(directions_world: Tensor) -> Tensor:
    """Colour ``(K, 3)`` of the sky seen along unit world-frame directions (clouds fixed in the world)."""
    up = directions_world[:, 2].clamp(-1, 1)
    blend = up.clamp(0, 1).sqrt()[:, None]
    horizon, zenith = torch.tensor([0.78, 0.83, 0.88]), torch.tensor([0.30, 0.50, 0.84])
    base = horizon * (1 - blend) + zenith * blend
    plane = directions_world[:, :2] / up.clamp_min(0.05)[:, None] * 1000.0  # a cloud deck 1 km up
    cloud = ((fbm(plane, 900.0, octaves=3, seed=21) - 0.5) * 3).clamp(0, 1) * (up > 0).float()
    return base * (1 - cloud[:, None] * 0.8) + 0.95 * cloud[:, None] * 0.8


def shade(albedo: Tensor, normals: Tensor, sun: Tensor) -> Tensor:
    """Lambertian shading ``(K, 3)`` in [0, 1]: sun light by ``max(0, n . sun)`` plus sky ambient.

    Args:
        albedo: ``(K, 3)``; normals: ``(K, 3)`` unit; sun: ``(3,)`` unit direction *towards* the sun,
            same frame as the normals.
    """
    direct = (normals @ sun).clamp_min(0)
    sky = 0.5 + 0.5 * normals[:, 2]
    light = 0.28 + 0.17 * sky + 0.75 * direct
    return (albedo * light[:, None]).clamp(0, 1)


def lidar_reflectivity(labels: Tensor, marking: Tensor | None = None) -> Tensor:
    """``(K,)`` reflectivity per hit class; painted road markings are retro-reflective."""
    out = REFLECTIVITY[labels.clamp(0, len(REFLECTIVITY) - 1)]
    if marking is not None:
        out = torch.where(marking > 0, torch.full_like(out, 0.9), out)
    return out
