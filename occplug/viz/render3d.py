"""A 3D view of an occupancy grid, ray cast with the project's own exact voxel traversal.

The view is an ordinary pinhole camera (:class:`ViewCamera`, OpenCV axes, placed in the ego frame
by a look-at pose), so its rays come from :func:`occplug.geometry.camera_rays` and every pixel is
resolved exactly by :func:`occplug.geometry.first_hit`: the first occupied voxel along the pixel's
ray and the distance at which the ray enters it. The face the ray enters through is the axis
whose slab the ray crosses last (the slab method), which gives the face normal; faces are shaded
by that normal, voxel edges are darkened, and rays that hit nothing show the grid's floor (with
a 10 m grid) or the background.

Cost: one traversal step per voxel crossed, vectorised over all pixels. Empty space is skipped
twice: the grid is cropped to the bounding box of its occupied voxels, and
:func:`coarse_to_fine_first_hit` first traverses a grid of 4 x 4 x 4 blocks, then the voxels from
the first occupied block on (same result as a plain :func:`~occplug.geometry.first_hit`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from occplug.geometry import GridSpec, camera_rays, first_hit

from .style import BACKGROUND, EGO_COLOR, FLOOR, FLOOR_LINE, Palette

__all__ = [
    "FACE_SHADE",
    "ViewCamera",
    "ViewHits",
    "cast_view",
    "coarse_to_fine_first_hit",
    "default_view",
    "look_at",
    "render_voxels",
]

#: Brightness of each face by its outward normal, ``(axis, sign)``: lit from above and slightly
#: from the ego's right-rear, so the faces a behind-above camera sees differ clearly.
FACE_SHADE: dict[tuple[int, int], float] = {
    (2, 1): 1.00,  # top
    (2, -1): 0.45,  # bottom
    (0, -1): 0.80,  # rear (facing a camera behind the ego)
    (0, 1): 0.62,  # front
    (1, -1): 0.88,  # right side
    (1, 1): 0.68,  # left side
}
_EDGE_PIXELS = 1.0  # width of the darkened voxel edges, pixels
_EDGE_SHADE = 0.72  # brightness on an edge of a voxel seen large; edges fade out on small voxels
#: The ego vehicle as a box in the ego frame (nuScenes origin: rear axle on the ground).
EGO_BOX = ((-1.0, -0.95, 0.0), (3.6, 0.95, 1.6))


def look_at(eye: Tensor, target: Tensor, up: Tensor | None = None) -> Tensor:
    """``(4, 4)`` float64 camera -> ego pose of an OpenCV camera at ``eye`` looking at ``target``.

    Args:
        eye, target: ``(3,)`` ego-frame points, metres.
        up: ``(3,)`` the world's up direction (default +z); the image's "down" is ``-up``. A
            camera looking straight along ``up`` has +x (ego forward) at the top of its image.
    """
    eye, target = eye.double(), target.double()
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) if up is None else up.double()
    z = torch.nn.functional.normalize(target - eye, dim=0)
    side = torch.linalg.cross(z, up)
    if side.norm() < 1e-9:  # looking straight along ``up``: the image's up is +x instead
        side = torch.linalg.cross(z, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    x = torch.nn.functional.normalize(side, dim=0)
    y = torch.linalg.cross(z, x)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = torch.stack([x, y, z], dim=1)
    pose[:3, 3] = eye
    return pose


@dataclass(frozen=True)
class ViewCamera:
    """A virtual pinhole camera for the 3D view.

    Attributes:
        eye, target: ego-frame positions (metres) of the camera and the point it looks at.
        fov_deg: vertical field of view, degrees.
        width, height: image size, pixels.
    """

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    fov_deg: float = 50.0
    width: int = 640
    height: int = 400

    def intrinsics(self) -> Tensor:
        """``(3, 3)`` float64 ``K`` (square pixels, principal point at the image centre)."""
        f = (self.height / 2) / math.tan(math.radians(self.fov_deg) / 2)
        return torch.tensor(
            [[f, 0.0, (self.width - 1) / 2], [0.0, f, (self.height - 1) / 2], [0.0, 0.0, 1.0]], dtype=torch.float64
        )

    def cam_to_ego(self) -> Tensor:
        """``(4, 4)`` float64 camera -> ego pose (:func:`look_at`)."""
        return look_at(torch.tensor(self.eye), torch.tensor(self.target))


def default_view(grid: GridSpec, width: int = 640, height: int = 400) -> ViewCamera:
    """Perspective from behind and above the ego, framing the whole grid."""
    x0, y0, z0, x1, y1, _ = grid.range
    half = max(x1 - x0, y1 - y0) / 2
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    eye = (cx - 1.45 * half, cy, z0 + 1.25 * half)
    target = (cx + 0.02 * half, cy, z0)
    return ViewCamera(eye=eye, target=target, fov_deg=50.0, width=width, height=height)


@dataclass
class ViewHits:
    """What each pixel of a view sees (``H x W`` image).

    Attributes:
        voxel: ``(H, W, 3)`` int64 index of the first occupied voxel, ``-1`` where none.
        distance: ``(H, W)`` float64 entry distance along the unit ray, metres (``inf``: none).
        axis: ``(H, W)`` int64 axis of the entered face (0 x, 1 y, 2 z), ``-1`` where none or
            where the camera sits inside the voxel.
        sign: ``(H, W)`` int64 sign of that face's outward normal (``+1`` / ``-1``, 0 where none).
        local: ``(H, W, 3)`` float64 hit point inside its voxel, in voxel units ``[0, 1]^3``.
        floor: ``(H, W)`` bool, no voxel hit but the ray meets the grid's floor (``z = z_min``)
            inside the grid's x/y range; ``floor_xy`` ``(H, W, 2)`` is where (metres).
        ego: ``(H, W)`` bool, the ego box is the nearest surface; ``ego_axis``/``ego_sign`` its face.
    """

    voxel: Tensor
    distance: Tensor
    axis: Tensor
    sign: Tensor
    local: Tensor
    floor: Tensor
    floor_xy: Tensor
    ego: Tensor
    ego_axis: Tensor
    ego_sign: Tensor


def _bbox_grid(occupied: Tensor, grid: GridSpec) -> tuple[Tensor, GridSpec, Tensor] | None:
    """The occupied voxels' bounding box as a sub-grid: ``(offset (3,), sub-grid, cropped occupancy)``."""
    nz = occupied.nonzero()
    if nz.numel() == 0:
        return None
    lo, hi = nz.amin(0), nz.amax(0) + 1
    lower = torch.tensor(grid.lower, dtype=torch.float64)
    size = torch.tensor(grid.voxel_size, dtype=torch.float64)
    rng = torch.cat([lower + lo * size, lower + hi * size]).tolist()
    sub = GridSpec(range=rng, voxel_size=grid.voxel_size)
    crop = occupied[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
    return lo, sub, crop


def coarse_to_fine_first_hit(
    occupied: Tensor, grid: GridSpec, origins: Tensor, directions: Tensor, block: int = 4
) -> tuple[Tensor, Tensor]:
    """:func:`~occplug.geometry.first_hit` with empty-space skipping, for rays of unlimited length.

    The voxels are grouped in ``block``-sized cubes; a ray's first occupied voxel lies in the first
    occupied block it enters, so the exact voxel traversal starts at that block's entry distance
    ``t_block`` (block faces are voxel faces, so distances stay exact) and the hit distance is
    ``t_block`` plus the distance from there.

    Args:
        occupied: ``(X, Y, Z)`` bool on ``grid``.
        grid: the voxel grid.
        origins: ``(R, 3)``; directions: ``(R, 3)`` unit; ego frame, metres.
        block: block edge in voxels (1 = plain :func:`~occplug.geometry.first_hit`).

    Returns:
        As :func:`~occplug.geometry.first_hit`: ``(R, 3)`` int64 hit voxel (``-1`` none) and
        ``(R,)`` entry distance (``inf`` none).
    """
    origins, directions = origins.to(torch.float64), directions.to(torch.float64)
    if block <= 1 or min(grid.shape) < block:
        hit, t = first_hit(occupied, grid, origins, directions, torch.inf)
        return hit, t.to(torch.float64)
    shape = torch.tensor(grid.shape)
    padded = ((shape + block - 1) // block) * block
    occ = torch.nn.functional.pad(
        occupied.bool(), (0, int(padded[2] - shape[2]), 0, int(padded[1] - shape[1]), 0, int(padded[0] - shape[0]))
    )
    nb = (padded // block).tolist()
    coarse = occ.reshape(nb[0], block, nb[1], block, nb[2], block).any(dim=5).any(dim=3).any(dim=1)
    lower = torch.tensor(grid.lower, dtype=torch.float64)
    size = torch.tensor(grid.voxel_size, dtype=torch.float64)
    coarse_grid = GridSpec(
        range=torch.cat([lower, lower + padded * size]).tolist(), voxel_size=[v * block for v in grid.voxel_size]
    )
    c_hit, t_block = first_hit(coarse, coarse_grid, origins, directions, torch.inf)
    hit = torch.full_like(c_hit, -1)
    dist = torch.full_like(t_block, torch.inf, dtype=torch.float64)
    rows = torch.nonzero(c_hit[:, 0] >= 0).squeeze(1)
    if rows.numel():
        t0 = t_block[rows].to(torch.float64)
        f_hit, f_t = first_hit(
            occupied, grid, origins[rows] + t0[:, None] * directions[rows], directions[rows], torch.inf
        )
        found = f_hit[:, 0] >= 0
        hit[rows[found]] = f_hit[found]
        dist[rows[found]] = t0[found] + f_t[found].to(torch.float64)
    return hit, dist


def _entry_face(origins: Tensor, dirs: Tensor, box_lo: Tensor, box_hi: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Slab test of rays against boxes (all ``(R, 3)`` float64).

    Returns ``t_enter (R,)``, ``t_exit (R,)``, the axis ``(R,)`` whose slab is entered last (the
    face the ray enters through) and that face's outward normal sign ``(R,)``.
    """
    moving = dirs != 0
    safe = torch.where(moving, dirs, torch.ones_like(dirs))
    t_a, t_b = (box_lo - origins) / safe, (box_hi - origins) / safe
    inside = (origins >= box_lo) & (origins <= box_hi)
    t_near = torch.where(moving, torch.minimum(t_a, t_b), torch.where(inside, -torch.inf, torch.inf))
    t_far = torch.where(moving, torch.maximum(t_a, t_b), torch.where(inside, torch.inf, -torch.inf))
    t_enter, axis = t_near.max(dim=-1)
    sign = -torch.sign(dirs.gather(-1, axis[:, None])[:, 0]).long()
    return t_enter, t_far.amin(dim=-1), axis, sign


def cast_view(occupied: Tensor, grid: GridSpec, view: ViewCamera, ego_box: bool = True) -> ViewHits:
    """Cast one ray per pixel of ``view`` through ``occupied`` ``(X, Y, Z)`` bool on ``grid``."""
    h, w = view.height, view.width
    origin, dirs, _ = camera_rays(view.intrinsics(), view.cam_to_ego(), h, w)
    dirs = dirs.reshape(-1, 3)
    origins = origin.expand_as(dirs)
    r = dirs.shape[0]
    voxel = torch.full((r, 3), -1, dtype=torch.int64)
    dist = torch.full((r,), torch.inf, dtype=torch.float64)
    crop = _bbox_grid(occupied.bool().cpu(), grid)
    if crop is not None:
        offset, sub, occ = crop
        hit, dist = coarse_to_fine_first_hit(occ, sub, origins, dirs)
        found = hit[:, 0] >= 0
        voxel[found] = hit[found] + offset
    found = voxel[:, 0] >= 0
    lower = torch.tensor(grid.lower, dtype=torch.float64)
    size = torch.tensor(grid.voxel_size, dtype=torch.float64)
    axis = torch.full((r,), -1, dtype=torch.int64)
    sign = torch.zeros((r,), dtype=torch.int64)
    local = torch.zeros((r, 3), dtype=torch.float64)
    if found.any():
        lo = lower + voxel[found] * size
        _, _, ax, sg = _entry_face(origins[found], dirs[found], lo, lo + size)
        starts_inside = dist[found] <= 0
        axis[found] = torch.where(starts_inside, -1, ax)
        sign[found] = torch.where(starts_inside, 0, sg)
        point = origins[found] + dist[found, None] * dirs[found]
        local[found] = ((point - lo) / size).clamp(0.0, 1.0)
    # the floor of the grid, where nothing was hit
    z0 = grid.lower[2]
    t_floor = (z0 - origins[:, 2]) / torch.where(dirs[:, 2] < 0, dirs[:, 2], torch.full_like(dirs[:, 2], -1e-12))
    floor_xy = (origins + t_floor[:, None] * dirs)[:, :2]
    in_range = (floor_xy >= lower[:2]).all(-1) & (floor_xy < lower[:2] + size[:2] * torch.tensor(grid.shape[:2])).all(
        -1
    )
    floor = ~found & (dirs[:, 2] < 0) & (t_floor > 0) & in_range
    # the ego vehicle
    ego = torch.zeros((r,), dtype=torch.bool)
    ego_axis = torch.full((r,), -1, dtype=torch.int64)
    ego_sign = torch.zeros((r,), dtype=torch.int64)
    if ego_box:
        b_lo = torch.tensor(EGO_BOX[0], dtype=torch.float64)
        b_hi = torch.tensor(EGO_BOX[1], dtype=torch.float64)
        t_in, t_out, e_axis, e_sign = _entry_face(origins, dirs, b_lo, b_hi)
        ego = (t_in <= t_out) & (t_in > 0) & (t_in < dist)
        ego_axis, ego_sign = torch.where(ego, e_axis, -1), torch.where(ego, e_sign, 0)
        floor &= ~ego
    return ViewHits(
        voxel=voxel.reshape(h, w, 3),
        distance=dist.reshape(h, w),
        axis=axis.reshape(h, w),
        sign=sign.reshape(h, w),
        local=local.reshape(h, w, 3),
        floor=floor.reshape(h, w),
        floor_xy=floor_xy.reshape(h, w, 2),
        ego=ego.reshape(h, w),
        ego_axis=ego_axis.reshape(h, w),
        ego_sign=ego_sign.reshape(h, w),
    )


def _face_shade(axis: Tensor, sign: Tensor) -> Tensor:
    """``(...)`` float64 brightness of faces from :data:`FACE_SHADE` (1 where the axis is -1)."""
    table = torch.ones(3, 3, dtype=torch.float64)  # [axis, sign + 1]
    for (a, s), v in FACE_SHADE.items():
        table[a, s + 1] = v
    return torch.where(
        axis >= 0, table[axis.clamp_min(0), (sign + 1).clamp(0, 2)], torch.ones_like(axis, dtype=torch.float64)
    )


def render_voxels(
    labels: Tensor,
    grid: GridSpec,
    palette: Palette,
    view: ViewCamera | None = None,
    valid: Tensor | None = None,
    ego_box: bool = True,
) -> np.ndarray:
    """Render a semantic occupancy grid as seen from ``view``.

    Args:
        labels: ``(X, Y, Z)`` integer class ids on ``grid`` (ego frame).
        grid: the label grid.
        palette: class colours; free and ignored ids are empty space.
        view: the virtual camera (default: :func:`default_view`).
        valid: optional ``(X, Y, Z)`` bool; voxels outside it are not drawn.
        ego_box: draw the ego vehicle.

    Returns:
        ``(H, W, 3)`` uint8 RGB image.
    """
    view = view or default_view(grid)
    labels = labels.long().cpu()
    occ = palette.occupied(labels)
    if valid is not None:
        occ &= valid.bool().cpu()
    hits = cast_view(occ, grid, view, ego_box=ego_box)
    h, w = view.height, view.width
    found = hits.voxel[..., 0] >= 0
    out = torch.tensor(BACKGROUND, dtype=torch.float64).expand(h, w, 3).clone()
    # voxels: class colour x face shade x edge darkening
    idx = hits.voxel[found]
    cls = labels[idx[:, 0], idx[:, 1], idx[:, 2]]
    color = torch.from_numpy(palette.colors.astype(np.float64))[cls]
    shade = _face_shade(hits.axis[found], hits.sign[found])
    local = hits.local[found]
    edge_dist = torch.minimum(local, 1 - local)  # (F, 3) distance to the voxel's faces per axis
    on_face_axis = (
        torch.nn.functional.one_hot(hits.axis[found].clamp_min(0), 3).bool() & (hits.axis[found] >= 0)[:, None]
    )
    edge_dist = torch.where(on_face_axis, torch.inf, edge_dist)
    # a voxel's size on screen, pixels: f * size / distance; edges fade out below ~6 pixels
    voxel_px = view.intrinsics()[0, 0] * min(grid.voxel_size) / hits.distance[found].clamp_min(1e-6)
    near_edge = edge_dist.amin(dim=-1) < _EDGE_PIXELS / voxel_px
    strength = ((voxel_px - 6.0) / 10.0).clamp(0.0, 1.0)
    shade = torch.where(near_edge, shade * (1 - (1 - _EDGE_SHADE) * strength), shade)
    out[found] = color * shade[:, None]
    # the floor with a 10 m grid
    fxy = hits.floor_xy[hits.floor]
    frac = torch.remainder(fxy, 10.0)
    line = ((frac < 0.12) | (frac > 10.0 - 0.12)).any(-1)
    floor_rgb = torch.where(
        line[:, None], torch.tensor(FLOOR_LINE, dtype=torch.float64), torch.tensor(FLOOR, dtype=torch.float64)
    )
    out[hits.floor] = floor_rgb
    # the ego
    if hits.ego.any():
        ego_shade = _face_shade(hits.ego_axis[hits.ego], hits.ego_sign[hits.ego])
        out[hits.ego] = torch.tensor(EGO_COLOR, dtype=torch.float64) * ego_shade[:, None]
    return out.round().clamp(0, 255).to(torch.uint8).numpy()
