"""The data contract: one :class:`Frame` per sample, collated into a :class:`Batch`.

Frames of reference (all metres, right-handed):

* **ego**: the vehicle body frame at the frame's timestamp; x forward, y left, z up, origin on the
  ground below the rear-axle centre (nuScenes). Occupancy labels, boxes and predictions live here.
* **global**: a fixed world frame per scene; ``ego_to_global`` places the ego in it.
* **camera**: OpenCV (x right, y down, z forward); ``cam_to_ego`` places each camera.
* **lidar**: the LiDAR sensor frame (x forward, y left, z up); ``lidar_to_ego`` places it.

Image augmentation is never baked into the calibration: ``img_aug`` records it as a 3x3 matrix so
``img_aug @ intrinsics`` projects ego points exactly into the augmented image
(see :mod:`occplug.geometry.cameras`).

Every field that not every data set has is optional (``None``). A component that needs one states
so in its docstring and fails with a clear error when it is missing.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import torch
from torch import Tensor

__all__ = ["COLLATE_RULES", "Batch", "FieldRule", "Frame", "FrameCollator", "collate_frames", "field_rule"]


@dataclass
class Frame:
    """One sample: a timestamped set of sensor readings with its labels.

    Shapes use ``N`` cameras, images ``H x W``, ``P`` LiDAR points, ``M`` boxes, label grid
    ``X x Y x Z``.

    Attributes:
        images: ``(N, 3, H, W)`` float32 RGB in [0, 1] (after any augmentation).
        intrinsics: ``(N, 3, 3)`` float32, calibrated pinhole matrices of the original images.
        cam_to_ego: ``(N, 4, 4)`` float32, camera -> ego.
        img_aug: ``(N, 3, 3)`` float32, original pixel -> augmented pixel (identity if none).
        ego_to_global: ``(4, 4)`` float64, ego -> global (float64: global coordinates are large).
        timestamp: seconds since the scene start (float).
        scene: scene / sequence name (str); frames of one scene share it.
        frame_index: position of the frame in its scene, 0-based; frames are ``1 / fps`` apart.
        token: unique sample id (str), used to name prediction files.
        camera_names: the ``N`` camera names, in the order of the camera axis.
        lidar_to_ego: ``(4, 4)`` float32, LiDAR -> ego, or None without a LiDAR.
        points: ``(P, 4)`` float32 LiDAR points in the **lidar** frame: x, y, z, intensity in [0, 1].
        point_labels: ``(P,)`` int64 semantic ids of the points (label taxonomy of the data set).
        voxel_labels: ``(X, Y, Z)`` uint8 semantic ids in the **ego** frame (Occ3D: 17 = free;
            SemanticKITTI: 0 = empty, 255 = ignore).
        mask_camera: ``(X, Y, Z)`` bool, voxels observed by at least one camera ray (Occ3D).
        mask_lidar: ``(X, Y, Z)`` bool, voxels observed by at least one LiDAR ray (Occ3D).
        voxel_invalid: ``(X, Y, Z)`` bool, voxels the benchmark ignores (SemanticKITTI ``.invalid``).
        has_voxel_labels: False for a sample whose voxel labels must not be used for training
            (label-efficient splits); evaluation still reads them when present.
        boxes: ``(M, 9)`` float32 in the ego frame: centre x, y, z, size length (along heading),
            width, height, yaw (rad, about +z from +x), velocity vx, vy (m/s, ego frame).
        box_labels: ``(M,)`` int64 class ids (same taxonomy as the voxel labels).
        box_track_ids: ``(M,)`` int64 track ids, stable across the frames of a scene.
        depth: ``(N, H, W)`` float32 ground-truth camera-frame z per pixel (0 = no return); only
            data sets that have it (the synthetic world).
        semantics_2d: ``(N, H, W)`` int64 ground-truth class id per pixel, or None.
        pseudo_depth: ``(N, H, W)`` float32 depth predicted by an external model (0 = none).
        pseudo_semantics: ``(N, H, W)`` int64 2D semantics already mapped to the target classes
            (255 = unknown).
        pseudo_features: ``(N, F, h, w)`` float32 low-resolution per-camera feature maps.
        sequence_lidar_origins: ``(S, 3)`` float32 LiDAR sensor positions of every frame of this
            frame's scene, in **this** frame's ego frame (RayIoU casts its query rays from them).
        adjacent: frames of the same scene at other times, keyed by frame offset
            (``-1`` = previous, ``+1`` = next). Their poses give the relative ego motion.
        extras: data-set-specific and plugin-declared per-sample fields (collated by their
            :class:`FieldRule`, see :mod:`occplug.data.extensions`); keep tensors out of here where a
            field exists.
    """

    images: Tensor
    intrinsics: Tensor
    cam_to_ego: Tensor
    img_aug: Tensor
    ego_to_global: Tensor
    timestamp: float
    scene: str
    frame_index: int
    token: str
    camera_names: tuple[str, ...] = ()
    lidar_to_ego: Tensor | None = None
    points: Tensor | None = None
    point_labels: Tensor | None = None
    voxel_labels: Tensor | None = None
    mask_camera: Tensor | None = None
    mask_lidar: Tensor | None = None
    voxel_invalid: Tensor | None = None
    has_voxel_labels: bool = True
    boxes: Tensor | None = None
    box_labels: Tensor | None = None
    box_track_ids: Tensor | None = None
    depth: Tensor | None = None
    semantics_2d: Tensor | None = None
    pseudo_depth: Tensor | None = None
    pseudo_semantics: Tensor | None = None
    pseudo_features: Tensor | None = None
    sequence_lidar_origins: Tensor | None = None
    adjacent: dict[int, Frame] = field(default_factory=dict)
    extras: dict[str, Any] = field(default_factory=dict)

    @property
    def num_cameras(self) -> int:
        """``N``."""
        return int(self.images.shape[0])

    @property
    def image_size(self) -> tuple[int, int]:
        """``(H, W)`` of the images."""
        return int(self.images.shape[-2]), int(self.images.shape[-1])

    def points_in_ego(self) -> Tensor:
        """``(P, 3)`` LiDAR points in the ego frame."""
        if self.points is None or self.lidar_to_ego is None:
            raise ValueError(f"frame {self.token} has no LiDAR points")
        from occplug.geometry import transform_points

        return transform_points(self.lidar_to_ego.to(self.points.dtype), self.points[:, :3])


# Fields stacked along a new batch axis when present in every frame; the rest become lists.
_STACKED = (
    "images",
    "intrinsics",
    "cam_to_ego",
    "img_aug",
    "ego_to_global",
    "lidar_to_ego",
    "voxel_labels",
    "mask_camera",
    "mask_lidar",
    "voxel_invalid",
    "depth",
    "semantics_2d",
    "pseudo_depth",
    "pseudo_semantics",
    "pseudo_features",
)
_LISTED = ("points", "point_labels", "boxes", "box_labels", "box_track_ids", "sequence_lidar_origins")


def _apply(v: Any, fn: Callable[[Tensor], Tensor]) -> Any:
    """``v`` with ``fn`` applied to every tensor in it (in lists, dicts and batches). A module function: a recursive
    closure would make a reference cycle per call."""
    if isinstance(v, Tensor):
        return fn(v)
    if isinstance(v, list):
        return [_apply(x, fn) for x in v]
    if isinstance(v, dict):
        return {k: _apply(x, fn) for k, x in v.items()}
    if isinstance(v, Batch):
        return Batch(**{f.name: _apply(getattr(v, f.name), fn) for f in fields(v)})
    return v


@dataclass
class Batch:
    """Frames collated for a network: the :class:`Frame` fields with a leading batch axis ``B``.

    Dense fields are stacked (``images`` becomes ``(B, N, 3, H, W)``, ``voxel_labels``
    ``(B, X, Y, Z)`` ...); fields whose length varies per sample (``points``, ``point_labels``,
    ``boxes``, ``box_labels``, ``box_track_ids``, ``sequence_lidar_origins``) are lists of ``B`` tensors. ``timestamp`` is a
    ``(B,)`` float64 tensor, ``frame_index`` a ``(B,)`` int64 tensor, ``has_voxel_labels`` a
    ``(B,)`` bool tensor. ``extras[name]`` is a list of ``B`` values, or what the field's
    :class:`FieldRule` makes of them (a stacked / padded tensor). ``is_sequence_start`` is ``(B,)`` bool: the frame is the first of its
    scene in the data set (``Frame.extras["is_sequence_start"]``, else ``frame_index == 0``), so
    stream state must be reset; frames missing within a scene are not detected. ``adjacent`` maps an offset to the
    :class:`Batch` of those adjacent frames (every frame of a batch has the same offsets).
    """

    images: Tensor
    intrinsics: Tensor
    cam_to_ego: Tensor
    img_aug: Tensor
    ego_to_global: Tensor
    timestamp: Tensor
    frame_index: Tensor
    has_voxel_labels: Tensor
    is_sequence_start: Tensor
    scene: list[str]
    token: list[str]
    camera_names: tuple[str, ...] = ()
    lidar_to_ego: Tensor | None = None
    points: list[Tensor] | None = None
    point_labels: list[Tensor] | None = None
    voxel_labels: Tensor | None = None
    mask_camera: Tensor | None = None
    mask_lidar: Tensor | None = None
    voxel_invalid: Tensor | None = None
    boxes: list[Tensor] | None = None
    box_labels: list[Tensor] | None = None
    box_track_ids: list[Tensor] | None = None
    depth: Tensor | None = None
    semantics_2d: Tensor | None = None
    pseudo_depth: Tensor | None = None
    pseudo_semantics: Tensor | None = None
    pseudo_features: Tensor | None = None
    sequence_lidar_origins: list[Tensor] | None = None
    adjacent: dict[int, Batch] = field(default_factory=dict)
    extras: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.images.shape[0])

    @property
    def batch_size(self) -> int:
        """``B``."""
        return len(self)

    def to(self, device: torch.device | str) -> Batch:
        """A copy with every tensor moved to ``device``."""
        return _apply(self, lambda t: t.to(device))

    def pin_memory(self) -> Batch:
        """A copy with every tensor in pinned memory (called by ``DataLoader(pin_memory=True)``)."""
        return _apply(self, Tensor.pin_memory)

    def require(self, *names: str, by: str) -> None:
        """Raise a clear error if any of the named fields is missing (``by`` names the component)."""
        missing = [n for n in names if getattr(self, n) is None]
        if missing:
            raise ValueError(f"{by} needs batch field(s) {', '.join(missing)}, which the data set does not provide")


#: The collate rules of a per-sample field in ``Frame.extras``.
COLLATE_RULES = ("stack", "list", "pad")


@dataclass(frozen=True)
class FieldRule:
    """How ``Frame.extras[name]`` of the frames of a batch becomes ``Batch.extras[name]``.

    Attributes:
        collate: ``stack`` (equal-shape tensors -> one tensor with a leading ``B`` axis), ``list``
            (a list of ``B`` values) or ``pad`` (tensors of shape ``(L_i, ...)`` -> ``(B, max L_i, ...)``
            filled with ``pad_value``, plus ``extras[name + "_mask"]`` ``(B, max L_i)`` bool).
        pad_value: the fill of ``pad``.
    """

    collate: str = "list"
    pad_value: float = 0

    def __post_init__(self) -> None:
        if self.collate not in COLLATE_RULES:
            raise ValueError(f"unknown collate rule '{self.collate}' (valid: {', '.join(COLLATE_RULES)})")


def field_rule(spec: FieldRule | str | Mapping[str, Any], where: str = "field") -> FieldRule:
    """A :class:`FieldRule` from itself, a rule name or ``{collate: ..., pad_value: ...}``; errors name ``where``."""
    if isinstance(spec, FieldRule):
        return spec
    try:
        if isinstance(spec, str):
            return FieldRule(spec)
        if isinstance(spec, Mapping):
            unknown = sorted(set(spec) - {"collate", "pad_value"})
            if unknown:
                raise ValueError(f"unknown key '{unknown[0]}' (valid: collate, pad_value)")
            return FieldRule(str(spec.get("collate", "list")), float(spec.get("pad_value", 0)))
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None
    raise ValueError(f"{where}: expected one of {', '.join(COLLATE_RULES)} or {{collate, pad_value}}, got {spec!r}")


def _collate_extra(name: str, values: list[Any], rule: FieldRule | None) -> dict[str, Any]:
    if rule is None or rule.collate == "list":
        return {name: values}
    if any(v is None for v in values):
        raise ValueError(f"extras field '{name}' ({rule.collate}) is missing in some frames of a batch")
    tensors = [torch.as_tensor(v) for v in values]
    if rule.collate == "stack":
        shapes = {tuple(t.shape) for t in tensors}
        if len(shapes) > 1:
            raise ValueError(f"extras field '{name}' is collated by 'stack' but has shapes {sorted(shapes)}; use 'pad'")
        return {name: torch.stack(tensors)}
    tails = {tuple(t.shape[1:]) for t in tensors}
    if any(t.dim() == 0 for t in tensors) or len(tails) > 1:
        raise ValueError(
            f"extras field '{name}' is collated by 'pad' but its shapes {[tuple(t.shape) for t in tensors]} "
            "differ beyond the first axis"
        )
    longest = max(int(t.shape[0]) for t in tensors)
    out = tensors[0].new_full((len(tensors), longest, *tensors[0].shape[1:]), rule.pad_value)
    mask = torch.zeros(len(tensors), longest, dtype=torch.bool)
    for i, t in enumerate(tensors):
        out[i, : t.shape[0]] = t
        mask[i, : t.shape[0]] = True
    return {name: out, f"{name}_mask": mask}


class FrameCollator:
    """``collate_fn`` with collate rules for extra fields (picklable, for loader workers).

    Args:
        fields: ``Frame.extras`` field name -> :class:`FieldRule` (undeclared extras become lists).
    """

    def __init__(self, fields: Mapping[str, FieldRule] | None = None) -> None:
        self.fields = dict(fields or {})

    def __call__(self, frames: list[Frame]) -> Batch:
        return collate_frames(frames, self.fields)


def collate_frames(frames: list[Frame], fields: Mapping[str, FieldRule] | None = None) -> Batch:
    """Collate frames into a :class:`Batch` (the ``collate_fn`` of every occplug data loader).

    Args:
        frames: the samples.
        fields: collate rules of ``Frame.extras`` fields; an undeclared extra becomes a list.
    """
    if not frames:
        raise ValueError("cannot collate an empty list of frames")
    first = frames[0]
    out: dict[str, Any] = {}
    for name in _STACKED:
        values = [getattr(f, name) for f in frames]
        if all(v is None for v in values):
            out[name] = None
        elif any(v is None for v in values):
            raise ValueError(f"field '{name}' is present in some frames of a batch but not others")
        else:
            out[name] = torch.stack(values)
    for name in _LISTED:
        values = [getattr(f, name) for f in frames]
        out[name] = None if all(v is None for v in values) else values
    out["timestamp"] = torch.tensor([f.timestamp for f in frames], dtype=torch.float64)
    out["frame_index"] = torch.tensor([f.frame_index for f in frames], dtype=torch.int64)
    out["has_voxel_labels"] = torch.tensor([f.has_voxel_labels for f in frames], dtype=torch.bool)
    out["is_sequence_start"] = torch.tensor(
        [bool(f.extras.get("is_sequence_start", f.frame_index == 0)) for f in frames], dtype=torch.bool
    )
    out["scene"] = [f.scene for f in frames]
    out["token"] = [f.token for f in frames]
    out["camera_names"] = first.camera_names
    offsets = set(first.adjacent)
    if any(set(f.adjacent) != offsets for f in frames):
        raise ValueError("every frame of a batch must carry the same adjacent-frame offsets")
    out["adjacent"] = {k: collate_frames([f.adjacent[k] for f in frames], fields) for k in sorted(offsets)}
    keys = set().union(*(f.extras for f in frames)) - {"is_sequence_start"}
    rules = fields or {}
    out["extras"] = {}
    for k in sorted(keys):
        out["extras"].update(_collate_extra(k, [f.extras.get(k) for f in frames], rules.get(k)))
    return Batch(**out)
