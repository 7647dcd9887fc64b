"""Augmentation of :class:`~occplug.data.Frame` objects, geometry-exact, on kornia.

Four independent parts, configured by one mapping (the ``augment`` argument of the data modules)::

    augment:
      photometric: strong          # none | weak | middle | strong (or a mapping, see PHOTOMETRIC_PRESETS)
      image: {size: [256, 704], scale: [0.9, 1.1], crop: random, flip: 0.5, rotate: [-5.4, 5.4]}
      bev: {flip_x: 0.5, flip_y: 0.5, rotate: [-22.5, 22.5], scale: [0.95, 1.05]}
      lidar: {dropout: 0.1, jitter: 0.02}

A plain string is the photometric preset alone (``augment: weak``).

**Image augmentation** (resize, crop, horizontal flip, rotation about the image centre) is one
``3 x 3`` matrix ``A`` per camera mapping original pixels to augmented pixels, in the pixel-centre
convention of :mod:`occplug.geometry.cameras` (the centre of pixel ``[row, col]`` is
``(u, v) = (col, row)``). It is composed into ``Frame.img_aug`` (``img_aug <- A @ img_aug``) and
every pixel field is warped with it: ``images`` (an antialiased resize, then a bilinear warp),
``depth``/``pseudo_depth`` and ``semantics_2d``/``pseudo_semantics`` (nearest neighbour, so
values are never blended; 0 / 255 where the augmented image shows nothing of the original) and
``pseudo_features`` (bilinear, at the features' own resolution). The calibration is untouched, so
``project_to_image(p, intrinsics, cam_to_ego, img_aug)`` lands on the same surface before and
after: a LiDAR point projects onto the pixel whose depth is its depth.

**BEV augmentation** is a similarity ``A = s R`` of the ego frame (``R`` a rotation about +z,
optionally composed with a flip of x and/or y; ``s`` a uniform scale). The whole sample moves with
it: a point ``p`` of the ego frame becomes ``A p``, and every sensor frame scales with the world,
which keeps all poses rigid and the images valid as they are:

* ``cam_to_ego``, ``lidar_to_ego`` ``[Q | t]`` -> ``[R Q | s R t]``; ``ego_to_global`` ``[Q | t]``
  -> ``[Q R^T | s t]`` (the global frame is scaled by ``s`` too, so relative ego motion stays a
  rigid ``A T A^-1``);
* LiDAR ``points`` (sensor frame) ``xyz *= s``; ``depth``/``pseudo_depth`` ``*= s``;
* ``boxes``: centre ``A c``, sizes ``* s``, heading rotated (and mirrored) by ``R``, velocity ``s R v``;
* ``sequence_lidar_origins``: ``A o``;
* ``voxel_labels``, ``mask_camera``, ``mask_lidar``, ``voxel_invalid``: resampled on the same grid,
  each voxel taking the source voxel under its centre's pre-image ``A^-1 c`` (exact for flips of a
  grid symmetric about the ego origin and for multiples of 90 degrees on square grids; nearest
  neighbour otherwise). Voxels whose pre-image leaves the grid become ``fill_label`` (the data
  set's ignore id), unobserved (masks False) and invalid.
* adjacent frames get the same ``A``; ``extras["bev_aug"]`` holds the ``(4, 4)`` float64 ``A``
  applied so far (compose its inverse to map predictions back).

After a flip the rotation parts have determinant -1; they are still orthogonal, which is all that
occplug's geometry (``invert_pose``, projection) relies on.

**LiDAR augmentation** (before the BEV transform, per frame, adjacent frames drawn independently):
point dropout keeps each point with probability ``1 - dropout``; jitter adds Gaussian noise of std
``jitter`` metres to the kept points' x, y, z in the LiDAR frame (intensity untouched);
``point_labels`` follow the kept points. Like ``img_aug`` it is recorded:
``extras["lidar_aug"]`` = ``{"keep": (P,) bool over the frame's original points, "offset": (P', 3)
float32 added to the kept points}``, and :func:`apply_lidar` re-applies a record exactly.

**Photometric presets** for teacher-student training change pixel values only (``img_aug`` is
untouched): ``weak`` = brightness / contrast / saturation / hue jitter; ``middle`` = stronger jitter
+ motion blur + weather (rain, snow or haze); ``strong`` = ``middle`` + cutout patches + sensor
noise. :func:`photometric` applies one to a ``(..., 3, H, W)`` tensor on any device, so a model can
also augment a batch it already holds (e.g. a student view of the teacher's batch).
"""

from __future__ import annotations

import contextlib
import copy
import math
from collections.abc import Callable, Iterator, Sequence
from contextvars import ContextVar
from dataclasses import dataclass, replace
from typing import Any

import torch
from kornia import augmentation as KA
from kornia.geometry.transform import resize as kornia_resize
from kornia.geometry.transform import warp_perspective
from torch import Tensor

from occplug.geometry import GridSpec

from .frame import Frame

__all__ = [
    "PHOTOMETRIC_PRESETS",
    "Augmentation",
    "BEVAugConfig",
    "ImageAugConfig",
    "ImageTransform",
    "LidarAugConfig",
    "apply_bev",
    "apply_lidar",
    "apply_image_transforms",
    "bev_matrix",
    "crop_matrix",
    "hflip_matrix",
    "photometric",
    "resize_matrix",
    "rotate_matrix",
    "seeded_draws",
]


# ---------------------------------------------------------------------------------------------
# pixel matrices (float64, original pixel -> new pixel, pixel-centre convention)


def resize_matrix(src_hw: Sequence[int], dst_hw: Sequence[int]) -> Tensor:
    """Resizing an ``src_hw`` image to ``dst_hw``: ``u' = sx (u + 0.5) - 0.5`` with ``sx = W'/W``."""
    sy, sx = dst_hw[0] / src_hw[0], dst_hw[1] / src_hw[1]
    return torch.tensor([[sx, 0.0, (sx - 1) / 2], [0.0, sy, (sy - 1) / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)


def crop_matrix(top: float, left: float) -> Tensor:
    """Cropping a window whose top-left pixel is ``(row=top, col=left)``: ``u' = u - left``."""
    return torch.tensor([[1.0, 0.0, -left], [0.0, 1.0, -top], [0.0, 0.0, 1.0]], dtype=torch.float64)


def hflip_matrix(width: int) -> Tensor:
    """Mirroring an image of ``width`` pixels left-right: ``u' = (W - 1) - u``."""
    return torch.tensor([[-1.0, 0.0, width - 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def rotate_matrix(degrees: float, hw: Sequence[int]) -> Tensor:
    """Rotating an ``hw`` image about its centre by ``degrees`` (counter-clockwise as displayed)."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    cu, cv = (hw[1] - 1) / 2, (hw[0] - 1) / 2
    # image rows grow downwards, so a counter-clockwise turn on screen is R(-a) in (u, v)
    rot = torch.tensor([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    to = torch.tensor([[1.0, 0.0, cu], [0.0, 1.0, cv], [0.0, 0.0, 1.0]], dtype=torch.float64)
    back = torch.tensor([[1.0, 0.0, -cu], [0.0, 1.0, -cv], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return to @ rot @ back


@dataclass(frozen=True)
class ImageTransform:
    """One camera's image transform: an (antialiased) resize to ``resized_hw``, then ``post``.

    ``matrix = post @ resize_matrix(src_hw, resized_hw)`` maps original pixels to output pixels;
    the output image is ``out_hw``.
    """

    src_hw: tuple[int, int]
    resized_hw: tuple[int, int]
    post: Tensor
    out_hw: tuple[int, int]

    @property
    def matrix(self) -> Tensor:
        """``(3, 3)`` float64 original pixel -> output pixel."""
        return self.post @ resize_matrix(self.src_hw, self.resized_hw)

    @classmethod
    def resize(cls, src_hw: Sequence[int], out_hw: Sequence[int]) -> ImageTransform:
        """A plain resize."""
        return cls(tuple(src_hw), tuple(out_hw), torch.eye(3, dtype=torch.float64), tuple(out_hw))  # type: ignore[arg-type]


def _warp(x: Tensor, matrix: Tensor, out_hw: tuple[int, int], mode: str) -> Tensor:
    """Warp ``(C, H, W)`` with a pixel matrix (kornia, pixel-index coordinates)."""
    out = warp_perspective(
        x[None].float(), matrix[None].to(torch.float32), out_hw, mode=mode, padding_mode="zeros", align_corners=True
    )
    return out[0]


def _is_identity(matrix: Tensor) -> bool:
    return bool(torch.allclose(matrix, torch.eye(3, dtype=matrix.dtype), atol=1e-12))


def _warp_labels(x: Tensor, matrix: Tensor, out_hw: tuple[int, int], fill: int) -> Tensor:
    """Nearest-neighbour warp of an integer map; ``fill`` where the output sees no input."""
    shifted = x.to(torch.float32) - fill + 1  # 0 marks "outside" after the warp (ids < 2**24 are exact)
    out = _warp(shifted[None], matrix, out_hw, "nearest")[0]
    return torch.where(out == 0, torch.full_like(out, float(fill)), out + fill - 1).round().to(x.dtype)


def _feature_hw(feat_hw: Sequence[int], image_hw: Sequence[int], out_hw: Sequence[int]) -> tuple[int, int]:
    return (max(1, round(out_hw[0] * feat_hw[0] / image_hw[0])), max(1, round(out_hw[1] * feat_hw[1] / image_hw[1])))


def apply_image_transforms(frame: Frame, transforms: Sequence[ImageTransform]) -> Frame:
    """A copy of ``frame`` with camera ``i`` transformed by ``transforms[i]`` (see the module docstring).

    Every transform must share ``out_hw`` (the cameras are stacked).
    """
    n = frame.num_cameras
    if len(transforms) != n:
        raise ValueError(f"{len(transforms)} image transforms for {n} cameras")
    out_hw = transforms[0].out_hw
    if any(t.out_hw != out_hw for t in transforms):
        raise ValueError("every camera of a frame must have the same augmented image size")
    src_hw = frame.image_size
    mats = torch.stack([t.matrix for t in transforms])
    images = []
    for cam, t in enumerate(transforms):
        img = frame.images[cam]
        if tuple(t.resized_hw) != tuple(src_hw):
            img = kornia_resize(img[None], t.resized_hw, interpolation="bilinear", align_corners=False, antialias=True)[
                0
            ]
        if not _is_identity(t.post) or tuple(t.resized_hw) != tuple(out_hw):
            img = _warp(img, t.post, out_hw, "bilinear")
        images.append(img.clamp(0, 1))
    out = copy.copy(frame)
    out.images = torch.stack(images)
    out.img_aug = (mats @ frame.img_aug.to(torch.float64)).to(frame.img_aug.dtype)
    for name in ("depth", "pseudo_depth"):
        value = getattr(frame, name)
        if value is not None:
            setattr(out, name, torch.stack([_warp(value[c][None], mats[c], out_hw, "nearest")[0] for c in range(n)]))
    for name in ("semantics_2d", "pseudo_semantics"):
        value = getattr(frame, name)
        if value is not None:
            setattr(out, name, torch.stack([_warp_labels(value[c], mats[c], out_hw, 255) for c in range(n)]))
    if frame.pseudo_features is not None:
        feats = frame.pseudo_features
        fh, fw = feats.shape[-2:]
        ofh, ofw = _feature_hw((fh, fw), src_hw, out_hw)
        warped = []
        for c in range(n):
            m = resize_matrix(out_hw, (ofh, ofw)) @ mats[c] @ torch.linalg.inv(resize_matrix(src_hw, (fh, fw)))
            warped.append(_warp(feats[c], m, (ofh, ofw), "bilinear").to(feats.dtype))
        out.pseudo_features = torch.stack(warped)
    out.adjacent = dict(frame.adjacent)
    out.extras = dict(frame.extras)
    return out


# ---------------------------------------------------------------------------------------------
# BEV


def bev_matrix(flip_x: bool = False, flip_y: bool = False, yaw: float = 0.0, scale: float = 1.0) -> Tensor:
    """``(4, 4)`` float64 ``A = s Rz(yaw) F``: flip (x -> -x and/or y -> -y), then rotate, then scale."""
    c, s = math.cos(yaw), math.sin(yaw)
    rot = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    flip = torch.diag(torch.tensor([-1.0 if flip_x else 1.0, -1.0 if flip_y else 1.0, 1.0], dtype=torch.float64))
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = scale * rot @ flip
    return out


def _split_similarity(a: Tensor) -> tuple[Tensor, float]:
    a3 = a[:3, :3].to(torch.float64)
    s = float(torch.linalg.det(a3).abs() ** (1 / 3))
    return a3 / s, s


def _sensor_pose(pose: Tensor, r: Tensor, s: float) -> Tensor:
    """``X_to_ego [Q | t]`` -> ``[R Q | s R t]``."""
    p = pose.to(torch.float64)
    out = p.clone()
    out[..., :3, :3] = r @ p[..., :3, :3]
    out[..., :3, 3] = s * (p[..., :3, 3] @ r.T)
    return out.to(pose.dtype)


def _resample_voxels(value: Tensor, grid: GridSpec, a: Tensor, fill: Any) -> Tensor:
    if tuple(value.shape) != tuple(grid.shape):
        raise ValueError(f"BEV augmentation: voxel grid {tuple(value.shape)} does not match the grid {grid.shape}")
    centres = grid.centers().to(torch.float64).reshape(-1, 3)
    r, s = _split_similarity(a)
    src = centres @ (r / s)  # A^-1 c = R^T c / s, row form
    idx = grid.coord_to_index(src)
    inside = grid.index_in_bounds(idx)
    flat = torch.full((centres.shape[0],), fill, dtype=value.dtype)
    i = idx[inside]
    flat[inside] = value[i[:, 0], i[:, 1], i[:, 2]]
    return flat.reshape(grid.shape)


def apply_bev(frame: Frame, a: Tensor, grid: GridSpec | None, fill_label: int = 255) -> Frame:
    """A copy of ``frame`` (and its adjacent frames) moved by the ego-frame similarity ``a`` (see the module docstring).

    Args:
        frame: the sample.
        a: ``(4, 4)`` similarity ``s R`` (rotation/flip about the ego origin, uniform scale, no translation).
        grid: the voxel grid of the frame's labels (needed when it has any).
        fill_label: the label of voxels whose pre-image leaves the grid.
    """
    a = a.to(torch.float64)
    r, s = _split_similarity(a)
    out = copy.copy(frame)
    out.cam_to_ego = _sensor_pose(frame.cam_to_ego, r, s)
    if frame.lidar_to_ego is not None:
        out.lidar_to_ego = _sensor_pose(frame.lidar_to_ego, r, s)
    e = frame.ego_to_global.to(torch.float64).clone()
    e[:3, :3] = e[:3, :3] @ r.T
    e[:3, 3] = s * e[:3, 3]
    out.ego_to_global = e.to(frame.ego_to_global.dtype)
    if frame.points is not None:
        pts = frame.points.clone()
        pts[:, :3] = pts[:, :3] * s
        out.points = pts
    for name in ("depth", "pseudo_depth"):
        value = getattr(frame, name)
        if value is not None:
            setattr(out, name, value * s)
    if frame.sequence_lidar_origins is not None:
        out.sequence_lidar_origins = (frame.sequence_lidar_origins.to(torch.float64) @ a[:3, :3].T).to(
            frame.sequence_lidar_origins.dtype
        )
    if frame.boxes is not None and frame.boxes.shape[0]:
        b = frame.boxes.to(torch.float64).clone()
        b[:, :3] = b[:, :3] @ a[:3, :3].T
        b[:, 3:6] = b[:, 3:6] * s
        heading = torch.stack([b[:, 6].cos(), b[:, 6].sin(), torch.zeros_like(b[:, 6])], -1) @ r.T
        yaw = torch.atan2(heading[:, 1], heading[:, 0])
        b[:, 6] = yaw - 2 * math.pi * torch.floor((yaw + math.pi) / (2 * math.pi))
        vel = torch.cat([b[:, 7:9], torch.zeros_like(b[:, :1])], -1) @ r.T
        b[:, 7:9] = s * vel[:, :2]
        out.boxes = b.to(frame.boxes.dtype)
    voxel_fields = {"voxel_labels": fill_label, "mask_camera": False, "mask_lidar": False, "voxel_invalid": True}
    for name, fill in voxel_fields.items():
        value = getattr(frame, name)
        if value is not None:
            if grid is None:
                raise ValueError("BEV augmentation of voxel labels needs the label grid")
            setattr(out, name, _resample_voxels(value, grid, a, fill))
    previous = frame.extras.get("bev_aug")
    out.extras = {**frame.extras, "bev_aug": a if previous is None else a @ previous.to(torch.float64)}
    out.adjacent = {k: apply_bev(v, a, grid, fill_label) for k, v in frame.adjacent.items()}
    return out


# ---------------------------------------------------------------------------------------------
# photometric presets

#: Photometric presets: each a mapping of stage -> settings (see :func:`photometric`).
PHOTOMETRIC_PRESETS: dict[str, dict[str, Any]] = {
    "none": {},
    "weak": {"jitter": {"brightness": 0.2, "contrast": 0.2, "saturation": 0.2, "hue": 0.03, "p": 0.8}},
    "middle": {
        "jitter": {"brightness": 0.3, "contrast": 0.3, "saturation": 0.3, "hue": 0.05, "p": 0.8},
        "motion_blur": {"p": 0.3},
        "weather": {"p": 0.3},
    },
    "strong": {
        "jitter": {"brightness": 0.4, "contrast": 0.4, "saturation": 0.4, "hue": 0.1, "p": 0.8},
        "motion_blur": {"p": 0.5},
        "weather": {"p": 0.5},
        "cutout": {"p": 0.7, "patches": 2, "scale": [0.02, 0.08]},
        "noise": {"p": 0.3, "std": 0.03},
    },
}
_PHOTOMETRIC_STAGES = {
    "jitter": ("brightness", "contrast", "saturation", "hue", "p"),
    "motion_blur": ("p", "kernel"),
    "weather": ("p",),
    "cutout": ("p", "patches", "scale"),
    "noise": ("p", "std"),
}


def _check_keys(mapping: Any, valid: Sequence[str], where: str) -> dict[str, Any]:
    if not isinstance(mapping, dict):
        raise ValueError(f"{where}: expected a mapping, got {type(mapping).__name__} {mapping!r}")
    from occplug.errors import closest

    for key in mapping:
        if key not in valid:
            hint = closest(str(key), list(valid))
            raise ValueError(
                f"{where}.{key}: unknown key{f'; did you mean {hint!r}?' if hint else ''} (valid: {', '.join(valid)})"
            )
    return mapping


def photometric_settings(spec: str | dict[str, Any] | None) -> dict[str, dict[str, Any]]:
    """Resolve a preset name or a mapping of stages into validated settings."""
    if spec is None:
        return {}
    if isinstance(spec, str):
        if spec not in PHOTOMETRIC_PRESETS:
            raise ValueError(f"augment.photometric: unknown preset '{spec}' (valid: {', '.join(PHOTOMETRIC_PRESETS)})")
        return copy.deepcopy(PHOTOMETRIC_PRESETS[spec])
    _check_keys(spec, list(_PHOTOMETRIC_STAGES), "augment.photometric")
    return {k: dict(_check_keys(v or {}, _PHOTOMETRIC_STAGES[k], f"augment.photometric.{k}")) for k, v in spec.items()}


def _haze(images: Tensor, strength: Tensor) -> Tensor:
    """Blend towards a light grey, more at the top of the image (far away) than at the bottom."""
    h = images.shape[-2]
    ramp = torch.linspace(1.0, 0.35, h, device=images.device, dtype=images.dtype).view(1, 1, h, 1)
    alpha = strength.view(-1, 1, 1, 1) * ramp
    return images * (1 - alpha) + 0.8 * alpha


def photometric(images: Tensor, spec: str | dict[str, Any] | None) -> Tensor:
    """Apply a photometric preset (``weak``/``middle``/``strong``) or settings to images.

    Args:
        images: ``(..., 3, H, W)`` float in [0, 1], any device; every image draws its own parameters.
        spec: preset name, mapping of stages (``jitter``, ``motion_blur``, ``weather``, ``cutout``,
            ``noise``), or None.

    Returns:
        Images of the same shape in [0, 1]; geometry is unchanged.
    """
    settings = photometric_settings(spec)
    if not settings:
        return images
    shape = images.shape
    x = images.reshape(-1, *shape[-3:]).float()
    b, _, h, w = x.shape
    dev = x.device
    if "jitter" in settings:
        j = settings["jitter"]
        aug = KA.ColorJiggle(
            j.get("brightness", 0.2),
            j.get("contrast", 0.2),
            j.get("saturation", 0.2),
            j.get("hue", 0.03),
            p=j.get("p", 1.0),
        )
        x = aug(x)
    if "motion_blur" in settings:
        m = settings["motion_blur"]
        k = int(m.get("kernel", max(3, (min(h, w) // 24) | 1)))
        k = max(3, k | 1)
        x = KA.RandomMotionBlur(kernel_size=(3, k) if k > 3 else 3, angle=35.0, direction=0.5, p=m.get("p", 1.0))(x)
    if "weather" in settings:
        p = float(settings["weather"].get("p", 1.0))
        pick = torch.randint(0, 3, (b,))
        active = torch.rand(b) < p
        area = h * w
        for kind in range(3):
            sel = (pick == kind) & active
            if not sel.any():
                continue
            sub = x[sel.to(dev)]
            if kind == 0:
                drops = (max(1, area // 400), max(2, area // 150))
                dh = (max(1, h // 40), max(2, h // 12))
                sub = KA.RandomRain(number_of_drops=drops, drop_height=dh, drop_width=(-2, 2), p=1.0)(sub)
            elif kind == 1:
                sub = KA.RandomSnow(snow_coefficient=(0.1, 0.4), brightness=(1.3, 2.0), p=1.0)(sub)
            else:
                sub = _haze(sub, torch.empty(sub.shape[0], device=dev).uniform_(0.2, 0.55))
            x[sel.to(dev)] = sub
    if "cutout" in settings:
        c = settings["cutout"]
        lo, hi = c.get("scale", (0.02, 0.08))
        for _ in range(int(c.get("patches", 1))):
            x = KA.RandomErasing(scale=(float(lo), float(hi)), ratio=(0.3, 3.3), value=0.0, p=c.get("p", 1.0))(x)
    if "noise" in settings:
        n = settings["noise"]
        x = KA.RandomGaussianNoise(std=float(n.get("std", 0.03)), p=n.get("p", 1.0))(x)
    return x.clamp(0, 1).to(images.dtype).reshape(shape)


# ---------------------------------------------------------------------------------------------
# configuration and the Augmentation callable


@dataclass(frozen=True)
class ImageAugConfig:
    """Random image augmentation (per camera).

    Attributes:
        size: output ``(H, W)``; None keeps the input size.
        scale: range of the resize factor, relative to the factor that makes the image just cover ``size``.
        crop: where the ``size`` window sits in the resized image: ``random``, ``center`` or
            ``bottom`` (bottom rows kept, horizontal position random: the sky is cut first).
        flip: probability of a horizontal flip.
        rotate: range of the rotation about the image centre, degrees.
    """

    size: tuple[int, int] | None = None
    scale: tuple[float, float] = (1.0, 1.0)
    crop: str = "random"
    flip: float = 0.0
    rotate: tuple[float, float] = (0.0, 0.0)

    @classmethod
    def from_config(cls, cfg: dict[str, Any]) -> ImageAugConfig:
        _check_keys(cfg, ("size", "scale", "crop", "flip", "rotate"), "augment.image")
        out = cls(
            size=None if cfg.get("size") is None else tuple(int(v) for v in cfg["size"]),  # type: ignore[arg-type]
            scale=tuple(float(v) for v in cfg.get("scale", (1.0, 1.0))),  # type: ignore[arg-type]
            crop=str(cfg.get("crop", "random")),
            flip=float(cfg.get("flip", 0.0)),
            rotate=tuple(float(v) for v in cfg.get("rotate", (0.0, 0.0))),  # type: ignore[arg-type]
        )
        if out.crop not in ("random", "center", "bottom"):
            raise ValueError(f"augment.image.crop: '{out.crop}' is not one of random, center, bottom")
        if out.size is not None and (len(out.size) != 2 or min(out.size) < 1):
            raise ValueError(f"augment.image.size: expected [H, W], got {cfg.get('size')}")
        if len(out.scale) != 2 or not 0 < out.scale[0] <= out.scale[1]:
            raise ValueError(f"augment.image.scale: expected [low, high] with 0 < low <= high, got {cfg.get('scale')}")
        return out

    def sample(self, src_hw: tuple[int, int], g: torch.Generator | None = None) -> ImageTransform:
        """Draw one camera's transform."""
        out_hw = self.size or src_hw
        u = lambda lo, hi: float(lo + (hi - lo) * torch.rand((), generator=g))  # noqa: E731
        base = max(out_hw[0] / src_hw[0], out_hw[1] / src_hw[1])
        f = base * u(*self.scale)
        resized = (max(1, round(src_hw[0] * f)), max(1, round(src_hw[1] * f)))
        dh, dw = resized[0] - out_hw[0], resized[1] - out_hw[1]
        if self.crop == "center":
            top, left = dh / 2, dw / 2
        elif self.crop == "bottom":
            top, left = float(dh), u(min(0, dw), max(0, dw))
        else:
            top, left = u(min(0, dh), max(0, dh)), u(min(0, dw), max(0, dw))
        top, left = float(round(top)), float(round(left))
        post = crop_matrix(top, left)
        if self.flip > 0 and float(torch.rand((), generator=g)) < self.flip:
            post = hflip_matrix(out_hw[1]) @ post
        if self.rotate != (0.0, 0.0):
            post = rotate_matrix(u(*self.rotate), out_hw) @ post
        return ImageTransform(tuple(src_hw), resized, post, tuple(out_hw))  # type: ignore[arg-type]


@dataclass(frozen=True)
class BEVAugConfig:
    """Random BEV augmentation (one draw per sample, shared by its adjacent frames).

    Attributes:
        flip_x: probability of mirroring x (forward/backward).
        flip_y: probability of mirroring y (left/right).
        rotate: range of the rotation about +z, degrees.
        scale: range of the uniform scale.
    """

    flip_x: float = 0.0
    flip_y: float = 0.0
    rotate: tuple[float, float] = (0.0, 0.0)
    scale: tuple[float, float] = (1.0, 1.0)

    @classmethod
    def from_config(cls, cfg: dict[str, Any]) -> BEVAugConfig:
        _check_keys(cfg, ("flip_x", "flip_y", "rotate", "scale"), "augment.bev")
        out = cls(
            flip_x=float(cfg.get("flip_x", 0.0)),
            flip_y=float(cfg.get("flip_y", 0.0)),
            rotate=tuple(float(v) for v in cfg.get("rotate", (0.0, 0.0))),  # type: ignore[arg-type]
            scale=tuple(float(v) for v in cfg.get("scale", (1.0, 1.0))),  # type: ignore[arg-type]
        )
        if len(out.scale) != 2 or not 0 < out.scale[0] <= out.scale[1]:
            raise ValueError(f"augment.bev.scale: expected [low, high] with 0 < low <= high, got {cfg.get('scale')}")
        return out

    def sample(self, g: torch.Generator | None = None) -> Tensor:
        """Draw one ``(4, 4)`` similarity."""
        r = lambda: float(torch.rand((), generator=g))  # noqa: E731
        fx, fy = r() < self.flip_x, r() < self.flip_y
        yaw = math.radians(self.rotate[0] + (self.rotate[1] - self.rotate[0]) * r())
        s = self.scale[0] + (self.scale[1] - self.scale[0]) * r()
        return bev_matrix(fx, fy, yaw, s)


@dataclass(frozen=True)
class LidarAugConfig:
    """Random LiDAR augmentation (one draw per frame).

    Attributes:
        dropout: probability that a point is dropped.
        jitter: std of the Gaussian noise added to x, y, z, metres.
    """

    dropout: float = 0.0
    jitter: float = 0.0

    @classmethod
    def from_config(cls, cfg: dict[str, Any]) -> LidarAugConfig:
        _check_keys(cfg, ("dropout", "jitter"), "augment.lidar")
        out = cls(dropout=float(cfg.get("dropout", 0.0)), jitter=float(cfg.get("jitter", 0.0)))
        if not 0 <= out.dropout < 1:
            raise ValueError(f"augment.lidar.dropout: expected a probability in [0, 1), got {cfg.get('dropout')}")
        if out.jitter < 0:
            raise ValueError(f"augment.lidar.jitter: expected a std >= 0 (metres), got {cfg.get('jitter')}")
        return out

    def sample(self, num_points: int, g: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """Draw ``(keep (P,) bool, offset (P', 3) float32)`` for a scan of ``num_points``."""
        keep = torch.rand(num_points, generator=g) >= self.dropout
        offset = torch.randn(int(keep.sum()), 3, generator=g) * self.jitter
        return keep, offset


def apply_lidar(frame: Frame, keep: Tensor, offset: Tensor) -> Frame:
    """A copy of ``frame`` with its LiDAR points dropped / jittered as recorded (see the module docstring).

    Args:
        frame: a frame with ``points`` ``(P, 4)`` (lidar frame); ``point_labels`` ``(P,)`` follow.
        keep: ``(P,)`` bool, the points kept.
        offset: ``(P', 3)`` float32 added to the kept points' x, y, z, ``P' = keep.sum()``.

    Returns:
        The frame with ``extras["lidar_aug"] = {"keep": keep, "offset": offset}``.
    """
    if frame.points is None:
        raise ValueError(f"frame {frame.token}: LiDAR augmentation needs points")
    if keep.shape != (frame.points.shape[0],) or offset.shape != (int(keep.sum()), 3):
        raise ValueError(
            f"frame {frame.token}: a LiDAR record of {tuple(keep.shape)} / {tuple(offset.shape)} "
            f"does not fit {frame.points.shape[0]} points"
        )
    points = frame.points[keep].clone()
    points[:, :3] += offset.to(points.dtype)
    labels = None if frame.point_labels is None else frame.point_labels[keep]
    out = replace(frame, points=points, point_labels=labels, extras=dict(frame.extras))
    out.extras["lidar_aug"] = {"keep": keep, "offset": offset}
    return out


#: The seed of the stream run being read (:func:`seeded_draws`), or None: draw freely.
_RUN_SEED: ContextVar[int | None] = ContextVar("occplug_augment_run_seed", default=None)


@contextlib.contextmanager
def seeded_draws(seed: int | None) -> Iterator[None]:
    """Inside, every :class:`Augmentation` draws its geometric parameters (the per-camera image
    transforms and the BEV transform) from a generator seeded with ``seed``, so the frames of one
    stream run get the same draw: the relative pose of consecutive frames stays a rigid ``A T A^-1``
    (a per-frame BEV scale or rotation would break it). Photometric changes stay per frame.
    :class:`~occplug.data.sequences.StreamDataset` reads training items inside it."""
    token = _RUN_SEED.set(seed)
    try:
        yield
    finally:
        _RUN_SEED.reset(token)


class Augmentation:
    """Training-time augmentation of frames: image geometry, photometric preset, LiDAR, BEV.

    Args:
        config: a photometric preset name, or a mapping with keys ``photometric``, ``image``, ``bev``,
            ``lidar`` (see the module docstring); None or ``{}`` does nothing.
        grid: the voxel grid of the labels (for BEV augmentation).
        fill_label: label of voxels a BEV transform brings in from outside the grid.

    Raises:
        ValueError: an unknown key or preset, with its path (``augment.image.flp: ...``).
    """

    def __init__(
        self, config: str | dict[str, Any] | None, grid: GridSpec | None = None, fill_label: int = 255
    ) -> None:
        cfg: dict[str, Any] = {"photometric": config} if isinstance(config, str) else dict(config or {})
        _check_keys(cfg, ("photometric", "image", "bev", "lidar"), "augment")
        self.photometric = photometric_settings(cfg.get("photometric"))
        self.image = None if cfg.get("image") is None else ImageAugConfig.from_config(cfg["image"])
        self.bev = None if cfg.get("bev") is None else BEVAugConfig.from_config(cfg["bev"])
        self.lidar = None if cfg.get("lidar") is None else LidarAugConfig.from_config(cfg["lidar"])
        self.grid = grid
        self.fill_label = fill_label

    @property
    def active(self) -> bool:
        """Whether any part is configured."""
        return bool(self.photometric) or self.image is not None or self.bev is not None or self.lidar is not None

    def __call__(self, frame: Frame, generator: torch.Generator | None = None) -> Frame:
        """Augment ``frame`` and its adjacent frames (same image geometry per camera, same BEV transform).

        Without a ``generator``, inside :func:`seeded_draws` the draws come from that run's seed.
        """
        if generator is None and _RUN_SEED.get() is not None:
            generator = torch.Generator().manual_seed(int(_RUN_SEED.get()))  # type: ignore[arg-type]
        if self.image is not None:
            transforms = [self.image.sample(frame.image_size, generator) for _ in range(frame.num_cameras)]
            frame = _map_with_adjacent(frame, lambda f: apply_image_transforms(f, _retarget(transforms, f.image_size)))
        if self.photometric:
            frame = _map_with_adjacent(frame, lambda f: replace(f, images=photometric(f.images, self.photometric)))
        if self.lidar is not None:
            lidar = self.lidar
            frame = _map_with_adjacent(
                frame, lambda f: f if f.points is None else apply_lidar(f, *lidar.sample(f.points.shape[0], generator))
            )
        if self.bev is not None:
            frame = apply_bev(frame, self.bev.sample(generator), self.grid, self.fill_label)
        return frame


def _retarget(transforms: Sequence[ImageTransform], src_hw: tuple[int, int]) -> list[ImageTransform]:
    return [t if t.src_hw == tuple(src_hw) else replace(t, src_hw=tuple(src_hw)) for t in transforms]  # type: ignore[arg-type]


def _map_with_adjacent(frame: Frame, fn: Callable[[Frame], Frame]) -> Frame:
    out = fn(frame)
    out.adjacent = {k: fn(v) for k, v in frame.adjacent.items()}
    return out
