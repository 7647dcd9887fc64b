"""A Rerun recording (``.rrd``) of a sequence: scrub through time in the Rerun viewer.

Entities (``/world`` is the ego frame of the sequence's first frame; z up):

* ``world``: view coordinates (right-handed, z up) and the class annotation context (static),
  so class ids show as names and palette colours;
* ``world/ego_path``: the ego trajectory (static line strip);
* ``world/ego``: the ego pose of each frame (``Transform3D``);
* ``world/ego/cameras/<NAME>``: each camera as a pinhole (``img_aug @ K``, OpenCV axes) placed by
  ``cam_to_ego``, with its image;
* ``world/ego/lidar``: LiDAR points in the ego frame, coloured by range (distance from the
  sensor) on one scale for the whole recording: 0 to :func:`lidar_range_max` (the grid's farthest
  corner), farther points take the scale's last colour;
* ``world/ego/occupancy/gt`` and ``world/ego/occupancy/pred``: occupied voxels as boxes with class
  ids (surface voxels only: those with a free face-neighbour; the hidden interior is left out);
* ``world/ego/boxes``: 3D boxes with class ids and ``<class> #<track id>`` labels.

Timelines: ``frame`` (sequence number = ``Frame.frame_index``) and ``time`` (``Frame.timestamp``,
seconds). Frames are streamed: each is logged and dropped before the next is taken (the ego path,
static, is logged at the end), so a sequence of thousands of frames needs the memory of one.
Needs ``rerun-sdk`` (the ``viz`` extra).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from occplug.data.frame import Frame
from occplug.geometry import GridSpec, invert_pose

from .deps import require_matplotlib, require_rerun
from .style import Palette

__all__ = ["export_sequence", "lidar_range_max", "surface_voxels"]

_RANGE_CMAP = "turbo"


def surface_voxels(occupied: Tensor) -> Tensor:
    """``(X, Y, Z)`` bool: occupied voxels with at least one of their 6 face-neighbours free
    (outside the grid counts as free)."""
    occ = occupied.bool()
    pad = torch.nn.functional.pad(occ, (1, 1, 1, 1, 1, 1))
    inner = torch.ones_like(occ)
    for axis in range(3):
        for shift in (0, 2):
            sl = [slice(1, -1)] * 3
            sl[axis] = slice(shift, shift + occ.shape[axis])
            inner &= pad[tuple(sl)]
    return occ & ~inner


def _voxel_boxes(rr: Any, labels: Tensor, grid: GridSpec, palette: Palette) -> Any:
    occ = surface_voxels(palette.occupied(labels.long()))
    idx = occ.nonzero()
    centers = grid.index_to_coord(idx).numpy()
    half = np.asarray(grid.voxel_size, dtype=np.float32) / 2
    class_ids = labels.long()[occ].numpy().astype(np.uint16)
    return rr.Boxes3D(
        centers=centers, half_sizes=np.broadcast_to(half, centers.shape), class_ids=class_ids, fill_mode="solid"
    )


def lidar_range_max(grid: GridSpec) -> float:
    """The top of the recording's LiDAR range colour scale: the distance from the ego origin to
    the grid's farthest corner, rounded up to 10 m (Occ3D's grid: 60 m)."""
    corners = np.abs(np.asarray(grid.range, dtype=np.float64).reshape(2, 3)).max(axis=0)
    return max(10.0, math.ceil(float(np.linalg.norm(corners)) / 10.0) * 10.0)


def _range_colors(ranges: np.ndarray, vmax: float) -> np.ndarray:
    from matplotlib import colormaps

    return (colormaps[_RANGE_CMAP](np.clip(ranges / vmax, 0.0, 1.0))[:, :3] * 255).astype(np.uint8)


def _log_frame(
    rr: Any,
    rec: Any,
    frame: Frame,
    pred: Tensor | None,
    grid: GridSpec,
    palette: Palette,
    world_from_first: Tensor,
    range_max: float,
) -> None:
    pose = (invert_pose(world_from_first) @ frame.ego_to_global.double()).float().numpy()
    rec.log("world/ego", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
    names = list(frame.camera_names) or [f"cam_{i}" for i in range(frame.num_cameras)]
    k_eff = (frame.img_aug @ frame.intrinsics).float().numpy()
    h, w = frame.image_size
    for c, name in enumerate(names):
        path = f"world/ego/cameras/{name}"
        c2e = frame.cam_to_ego[c].float().numpy()
        rec.log(path, rr.Transform3D(translation=c2e[:3, 3], mat3x3=c2e[:3, :3]))
        rec.log(path, rr.Pinhole(image_from_camera=k_eff[c], resolution=[w, h], camera_xyz=rr.ViewCoordinates.RDF))
        image = (frame.images[c].clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
        rec.log(path, rr.Image(image))
    if frame.points is not None and frame.lidar_to_ego is not None:
        ego_pts = frame.points_in_ego().numpy()
        ranges = frame.points[:, :3].norm(dim=-1).numpy()
        rec.log(
            "world/ego/lidar",
            rr.Points3D(ego_pts, colors=_range_colors(ranges, range_max), radii=0.04),
        )
    if frame.voxel_labels is not None:
        rec.log("world/ego/occupancy/gt", _voxel_boxes(rr, frame.voxel_labels, grid, palette))
    if pred is not None:
        rec.log("world/ego/occupancy/pred", _voxel_boxes(rr, pred, grid, palette))
    if frame.boxes is not None and len(frame.boxes):
        b = frame.boxes.float().numpy()
        cls = frame.box_labels.numpy() if frame.box_labels is not None else np.zeros(len(b), np.int64)
        tracks = frame.box_track_ids.numpy() if frame.box_track_ids is not None else np.arange(len(b))
        labels = [
            f"{palette.names[c] if 0 <= c < palette.num_classes else c} #{t}" for c, t in zip(cls, tracks, strict=True)
        ]
        rec.log(
            "world/ego/boxes",
            rr.Boxes3D(
                centers=b[:, :3],
                half_sizes=b[:, 3:6] / 2,
                rotation_axis_angles=[rr.RotationAxisAngle(axis=[0.0, 0.0, 1.0], radians=float(y)) for y in b[:, 6]],
                class_ids=cls.astype(np.uint16),
                labels=labels,
            ),
        )
        rec.log("world/ego/boxes", rr.AnyValues(track_id=tracks.astype(np.int64)))


def export_sequence(
    frames: Iterable[Frame],
    path: str | Path,
    grid: GridSpec,
    palette: Palette,
    predictions: Iterable[Tensor | None] | None = None,
    recording_name: str | None = None,
    predict: Callable[[Frame], Tensor | None] | None = None,
    range_max: float | None = None,
) -> Path:
    """Write the frames of one sequence (in time order) as a Rerun recording, streaming them.

    ``frames`` (and ``predictions``) may be generators: each frame is logged and let go before
    the next is drawn, so nothing of a sequence is held but its ego poses.

    Args:
        frames: the sequence's frames, in time order (one scene).
        path: the ``.rrd`` file to write (parents created).
        grid: the label grid of ``voxel_labels`` and predictions (ego frame).
        palette: class names and colours (the annotation context).
        predictions: per frame, ``(X, Y, Z)`` predicted class ids or None (same order as frames).
        recording_name: a name shown in the viewer (default: the scene name).
        predict: instead of ``predictions``, called on each frame as it is logged.
        range_max: top of the LiDAR range colour scale, metres, for every frame (default
            :func:`lidar_range_max` of ``grid``).

    Returns:
        ``path``.

    Raises:
        ValueError: no frame, or not one prediction per frame (found when the shorter one ends;
            the file then holds the frames logged so far).
    """
    rr = require_rerun("--rerun")
    require_matplotlib("--rerun (LiDAR range colours)")
    if predictions is not None and predict is not None:
        raise ValueError("export_sequence takes predictions or predict, not both")
    frame_iter = iter(frames)
    head = next(frame_iter, None)
    if head is None:
        raise ValueError("export_sequence needs at least one frame")
    pred_iter = iter(predictions) if predictions is not None else None
    range_max = float(range_max) if range_max is not None else lidar_range_max(grid)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream("occplug", recording_id=f"occplug-{head.scene}")
    rec.save(str(path))
    if hasattr(rec, "send_recording_name"):
        rec.send_recording_name(recording_name or head.scene)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log(
        "world",
        rr.AnnotationContext(
            [(i, palette.names[i], tuple(int(v) for v in palette.colors[i])) for i in palette.semantic_ids()]
        ),
        static=True,
    )
    first = head.ego_to_global.double()
    frame: Frame | None = head
    del head
    positions: list[Tensor] = []
    try:
        while frame is not None:
            pred: Tensor | None = None
            if pred_iter is not None:
                pred = next(pred_iter, _MISSING)
                if pred is _MISSING:
                    raise ValueError(f"fewer predictions than frames (none for frame {len(positions)})")
            elif predict is not None:
                pred = predict(frame)
            rec.set_time("frame", sequence=int(frame.frame_index))
            rec.set_time("time", duration=float(frame.timestamp))
            _log_frame(rr, rec, frame, pred, grid, palette, first, range_max)
            positions.append((invert_pose(first) @ frame.ego_to_global.double())[:3, 3])
            frame = pred = None  # let go of this frame before the next one is loaded
            frame = next(frame_iter, None)
        if pred_iter is not None and next(pred_iter, _MISSING) is not _MISSING:
            raise ValueError(f"more predictions than the {len(positions)} frames")
        path_pts = torch.stack(positions).float().numpy()
        rec.log("world/ego_path", rr.LineStrips3D([path_pts], colors=[(255, 255, 255)]), static=True)
    finally:
        rec.flush()
        rec.disconnect()
    return path


_MISSING: Any = object()
