"""Sensors of the synthetic world: a surround camera rig and a spinning LiDAR, rendered by exact
ray casting against the scene's solids and ground plane (all in the ego frame)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor

from occplug.geometry import camera_rays, lidar_ray_directions

from .appearance import ground_albedo, lidar_reflectivity, shade, sky_color, solid_albedo
from .primitives import Primitives, intersect_rays, local_normal
from .world import GroundMap, Scene

__all__ = [
    "CAMERA_RIG",
    "LIDAR_TO_EGO",
    "NO_SURFACE",
    "Surface",
    "camera_rig",
    "corrupt_lidar",
    "lidar_generator",
    "render_cameras",
    "render_lidar",
    "trace",
]

#: ``semantics_2d`` value of pixels that see no surface (sky).
NO_SURFACE = 255

#: nuScenes-like rig: name, mount position in the ego frame (m), yaw (deg, CCW from +x), horizontal FOV (deg).
CAMERA_RIG: tuple[tuple[str, tuple[float, float, float], float, float], ...] = (
    ("CAM_FRONT", (1.70, 0.00, 1.51), 0.0, 70.0),
    ("CAM_FRONT_RIGHT", (1.55, -0.49, 1.51), -55.0, 70.0),
    ("CAM_FRONT_LEFT", (1.52, 0.49, 1.51), 55.0, 70.0),
    ("CAM_BACK", (0.03, 0.00, 1.58), 180.0, 110.0),
    ("CAM_BACK_LEFT", (1.04, 0.48, 1.59), 110.0, 70.0),
    ("CAM_BACK_RIGHT", (1.01, -0.48, 1.56), -110.0, 70.0),
)

#: LiDAR -> ego: on the roof (nuScenes LIDAR_TOP position), axes aligned with the ego's.
LIDAR_TO_EGO = torch.tensor(
    [[1.0, 0.0, 0.0, 0.94], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.84], [0.0, 0.0, 0.0, 1.0]], dtype=torch.float32
)

# OpenCV camera axes (x right, y down, z forward) expressed in the ego frame for a camera facing +x.
_CAM_AXES = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_rig(num_cameras: int, image_size: tuple[int, int]) -> tuple[tuple[str, ...], Tensor, Tensor]:
    """The first ``num_cameras`` cameras of :data:`CAMERA_RIG` for ``(H, W)`` images.

    Returns:
        names; ``intrinsics`` ``(N, 3, 3)`` float32 (square pixels, principal point at the image
        centre ``((W - 1) / 2, (H - 1) / 2)`` in the pixel-centre convention); ``cam_to_ego``
        ``(N, 4, 4)`` float32.
    """
    h, w = image_size
    names, ks, poses = [], [], []
    for name, position, yaw_deg, hfov_deg in CAMERA_RIG[:num_cameras]:
        f = (w / 2) / math.tan(math.radians(hfov_deg) / 2)
        ks.append(torch.tensor([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]]))
        yaw = math.radians(yaw_deg)
        rot_z = torch.tensor(
            [[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0.0, 0.0, 1.0]]
        )
        pose = torch.eye(4)
        pose[:3, :3] = rot_z @ _CAM_AXES
        pose[:3, 3] = torch.tensor(position)
        names.append(name)
        poses.append(pose)
    return tuple(names), torch.stack(ks), torch.stack(poses)


@dataclass
class Surface:
    """What each of ``R`` rays from one origin sees first.

    Attributes:
        t: ``(R,)`` float32 range along the unit ray, metres (``inf``: nothing within range).
        label: ``(R,)`` int64 Occ3D class, :data:`NO_SURFACE` for none.
        normal: ``(R, 3)`` float32 unit surface normal, ego frame (zero for none).
        solid: ``(R,)`` int64 index of the hit solid, ``-1`` for the ground or none.
        ground: ``(R,)`` bool, the ray hit the ground plane.
        ground_xy: ``(G, 2)`` world coordinates of the ground hits (``G = ground.sum()``).
        marking: ``(G,)`` int64 road paint at the ground hits (0 none, 1 white, 2 yellow).
        normal_unit: ``(R, 3)`` normal in the hit solid's unit frame (see :mod:`.primitives`).
    """

    t: Tensor
    label: Tensor
    normal: Tensor
    solid: Tensor
    ground: Tensor
    ground_xy: Tensor
    marking: Tensor
    normal_unit: Tensor


def trace(
    prims: Primitives,
    ground: GroundMap,
    ego_to_world: Tensor,
    origin: Tensor,
    directions: Tensor,
    max_range: float = math.inf,
    bundles: Tensor | None = None,
) -> Surface:
    """Cast rays sharing one ego-frame ``origin`` (above the ground) against solids and ground.

    Args:
        prims: solids in the ego frame.
        ground: the scene's ground map (world frame).
        ego_to_world: ``(4, 4)`` float64 pose used to look up ground classes and paint.
        origin: ``(3,)`` ego frame, metres.
        directions: ``(R, 3)`` unit, ego frame.
        max_range: hits farther than this count as none.
        bundles: ``(R,)`` int64 ids of coherent ray bundles, for culling (see
            :func:`~.primitives.intersect_rays`).
    """
    dz = directions[:, 2]
    t_ground = torch.where(dz < -1e-9, -origin[2] / dz.clamp(max=-1e-9), torch.full_like(dz, math.inf))
    hit = intersect_rays(prims, origin, directions, bundles, limit=t_ground.clamp(max=max_range))
    on_ground = t_ground < hit.t
    t = torch.where(on_ground, t_ground, hit.t)
    found = torch.isfinite(t) & (t <= max_range)
    on_ground &= found
    on_solid = found & ~on_ground
    t = torch.where(found, t, torch.full_like(t, math.inf))
    label = torch.full(t.shape, NO_SURFACE, dtype=torch.int64)
    normal = torch.zeros_like(directions)
    solid = torch.where(on_solid, hit.index, torch.full_like(hit.index, -1))
    ground_pts = origin + directions[on_ground] * t[on_ground, None]
    ground_xy = (ground_pts.double() @ ego_to_world[:3, :3].T + ego_to_world[:3, 3])[:, :2].float()
    label[on_ground] = ground.classes_at(ground_xy)
    normal[on_ground] = torch.tensor([0.0, 0.0, 1.0])
    if on_solid.any():
        label[on_solid] = prims.label[solid[on_solid]]
        normal[on_solid] = local_normal(prims, solid[on_solid], hit.normal_unit[on_solid])
    return Surface(t, label, normal, solid, on_ground, ground_xy, ground.marking_at(ground_xy), hit.normal_unit)


def _colors(
    surface: Surface, prims: Primitives, origin: Tensor, directions: Tensor, ego_to_world: Tensor, sun_ego: Tensor
) -> Tensor:
    """``(R, 3)`` shaded colour of each ray: ground and solids textured and lit, the rest sky."""
    rgb = sky_color(directions @ ego_to_world[:3, :3].float().T)
    g = surface.ground
    if g.any():
        albedo = ground_albedo(surface.label[g], surface.ground_xy, surface.marking)
        rgb[g] = shade(albedo, surface.normal[g], sun_ego)
    s = surface.solid >= 0
    if s.any():
        idx = surface.solid[s]
        sub = prims.select(idx)
        points = origin + directions[s] * surface.t[s, None]
        local = sub.to_local(points)
        face_axis = surface.normal_unit[s].abs().argmax(-1)
        albedo = solid_albedo(sub.material, sub.color, local, sub.half, face_axis)
        rgb[s] = shade(albedo, surface.normal[s], sun_ego)
    return rgb


@dataclass
class CameraImages:
    """Rendered cameras: ``images (N, 3, H, W)`` in [0, 1], ``depth (N, H, W)`` camera-frame z
    (0 = no surface), ``semantics (N, H, W)`` int64 (:data:`NO_SURFACE` for sky), ``ranges (N, H, W)``
    metres along each pixel ray (``inf`` = sky) and the pixel rays ``directions (N, H, W, 3)``
    (ego frame) from ``origins (N, 3)``."""

    images: Tensor
    depth: Tensor
    semantics: Tensor
    ranges: Tensor
    directions: Tensor
    origins: Tensor


def render_cameras(
    prims: Primitives,
    ground: GroundMap,
    ego_to_world: Tensor,
    sun_ego: Tensor,
    intrinsics: Tensor,
    cam_to_ego: Tensor,
    image_size: tuple[int, int],
    noise: float,
    generator: torch.Generator,
) -> CameraImages:
    """Render every camera: one ray through each pixel centre.

    Args:
        prims: solids in the ego frame.
        ground: ground map; ego_to_world: ``(4, 4)`` float64.
        sun_ego: ``(3,)`` unit vector towards the sun, ego frame.
        intrinsics: ``(N, 3, 3)``; cam_to_ego: ``(N, 4, 4)``; image_size: ``(H, W)``.
        noise: standard deviation of additive Gaussian sensor noise.
        generator: seeds the sensor noise.

    Images are quantised to 8-bit levels (multiples of 1/255).
    """
    h, w = image_size
    origins, directions, z_per_metre = camera_rays(intrinsics, cam_to_ego, h, w)
    n = intrinsics.shape[0]
    tiles = _tile_ids(h, w)
    images = torch.empty(n, 3, h, w)
    ranges = torch.empty(n, h, w)
    semantics = torch.empty(n, h, w, dtype=torch.int64)
    for cam in range(n):
        dirs = directions[cam].reshape(-1, 3)
        surface = trace(prims, ground, ego_to_world, origins[cam], dirs, bundles=tiles)
        rgb = _colors(surface, prims, origins[cam], dirs, ego_to_world, sun_ego)
        images[cam] = rgb.T.reshape(3, h, w)
        ranges[cam] = surface.t.reshape(h, w)
        semantics[cam] = surface.label.reshape(h, w)
    if noise > 0:
        images = images + noise * torch.randn(images.shape, generator=generator)
    # 8-bit levels like a real camera's output (and exactly representable as uint8 on disk)
    images = torch.round(images.clamp(0, 1) * 255) / 255
    depth = torch.where(torch.isfinite(ranges), ranges * z_per_metre, torch.zeros_like(ranges))
    return CameraImages(images, depth, semantics, ranges, directions, origins)


def _tile_ids(height: int, width: int, tile: int = 32) -> Tensor:
    """``(H * W,)`` int64 id of the ``tile x tile`` pixel block of each pixel (row-major)."""
    rows = torch.arange(height)[:, None] // tile
    cols = torch.arange(width)[None, :] // tile
    return (rows * ((width + tile - 1) // tile) + cols).reshape(-1)


@dataclass
class LidarSweep:
    """One LiDAR revolution: ``points (P, 4)`` x, y, z (LiDAR frame) and intensity in [0, 1],
    ``labels (P,)`` int64, ``origin (3,)`` the sensor in the ego frame."""

    points: Tensor
    labels: Tensor
    origin: Tensor


def render_lidar(
    prims: Primitives,
    ground: GroundMap,
    ego_to_world: Tensor,
    beams: int,
    elevation_deg: tuple[float, float],
    azimuth_steps: int,
    max_range: float,
    lidar_to_ego: Tensor = LIDAR_TO_EGO,
    sectors: int = 12,
) -> LidarSweep:
    """Fire every beam at every azimuth step; keep returns within ``max_range``.

    Intensity is the class reflectivity (road paint: high) times the cosine of the incidence angle.
    The ego vehicle is not part of the scene, so there are no self-hits. Points are ordered by
    beam (lowest first), then azimuth.
    """
    elevations = torch.linspace(elevation_deg[0], elevation_deg[1], beams)
    dirs_lidar = lidar_ray_directions(elevations, azimuth_steps)  # (B, A, 3)
    # bundles: azimuth sectors, for culling
    sector = (torch.arange(azimuth_steps) * sectors // azimuth_steps).expand(beams, -1).reshape(-1)
    d_l = dirs_lidar.reshape(-1, 3)
    d_e = d_l @ lidar_to_ego[:3, :3].T
    origin = lidar_to_ego[:3, 3]
    surface = trace(prims, ground, ego_to_world, origin, d_e, max_range, bundles=sector)
    keep = torch.isfinite(surface.t)
    t = surface.t[keep]
    cos_inc = (surface.normal[keep] * d_e[keep]).sum(-1).abs()
    marking = torch.zeros_like(surface.label)
    marking[surface.ground] = surface.marking
    intensity = (lidar_reflectivity(surface.label[keep], marking[keep]) * cos_inc).clamp(0, 1)
    points = torch.cat([d_l[keep] * t[:, None], intensity[:, None]], -1)
    return LidarSweep(points, surface.label[keep], origin)


def lidar_generator(scene: Scene, frame_index: int) -> torch.Generator:
    """The generator of frame ``frame_index``'s LiDAR corruption (a stream of its own: the image noise
    and the scene draws are untouched, so switching corruption on changes nothing else)."""
    state = np.random.SeedSequence([scene.seed, frame_index, 0x11DA4]).generate_state(2, np.uint64)
    return torch.Generator().manual_seed(int(state[0]) % (1 << 62))


def corrupt_lidar(sweep: LidarSweep, range_noise: float, dropout: float, generator: torch.Generator) -> LidarSweep:
    """A sweep with Gaussian range noise and random dropout of returns.

    Each return moves along its own ray by ``N(0, range_noise**2)`` metres (clamped to stay in front
    of the sensor), then is dropped with probability ``dropout``; labels and intensities follow their
    points. With both 0 the sweep is returned unchanged.

    Args:
        sweep: points ``(P, 4)`` in the LiDAR frame (the sensor at the origin).
        range_noise: standard deviation, metres.
        dropout: in ``[0, 1)``.
        generator: seeds both draws.
    """
    if range_noise == 0 and dropout == 0:
        return sweep
    pts = sweep.points
    xyz = pts[:, :3]
    r = xyz.norm(dim=-1, keepdim=True)
    noisy = r + range_noise * torch.randn(r.shape, generator=generator, dtype=r.dtype)
    xyz = xyz * (noisy.clamp_min(1e-3) / r.clamp_min(1e-9))
    keep = torch.rand(r.shape[0], generator=generator) >= dropout
    points = torch.cat([xyz, pts[:, 3:]], -1)[keep]
    return replace(sweep, points=points, labels=sweep.labels[keep])
