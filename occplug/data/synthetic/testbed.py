"""Floors, ceilings and headroom of the synthetic world under each evaluation protocol (issue 52).

:func:`measure` reads a world's validation split under every evaluation mask and readout a method uses
and returns, per mask, the **floor** (predictions that look at no image: all free, all of the most
frequent occupied class, the per-voxel most frequent class of the training split), the **ideal-field
ceiling** (:mod:`.field` read through each readout), the **perfect-depth ceiling**
(:func:`occplug.ceilings.depth_lift` of the true depth and 2D classes, at a feature stride) and the
**history headroom** (:func:`occplug.ceilings.history_headroom`), and what one LiDAR sweep gives away:
its returns voxelised with their classes (``lidar_sweep``: the geometry a LiDAR branch starts from). :func:`object_pixel_heights` reports
how tall the agents appear in the images, per class. ``python scripts/ceilings.py`` prints both.

Masks: ``camera`` (the rig's ``mask_camera``), ``camera1`` (the front camera's alone), ``lidar``
(``mask_lidar``) and ``none`` (every voxel).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from occplug.ceilings import (
    Headroom,
    Scorer,
    depth_lift,
    history_headroom,
    parse_readout,
    read_voxels,
    training_prior,
    vote_points,
)
from occplug.data.classes import OCC3D_CLASSES, OCC3D_FREE
from occplug.geometry import invert_pose, project_to_image

from .config import SyntheticWorldConfig
from .dataset import SyntheticDataset
from .field import DEFAULT_GROUND_SHELL, scene_field_samples
from .frames import frame_labels, rig_camera_mask
from .labels import agent_boxes, voxel_labels
from .render import camera_rig
from .world import build_scene

__all__ = ["HEADROOM_PROTOCOLS", "MASKS", "measure", "object_pixel_heights", "scene_field_samples"]

#: The evaluation masks :func:`measure` scores under.
MASKS: tuple[str, ...] = ("camera", "camera1", "lidar", "none")

#: History headroom: ``name -> (what the sensors observe, what the protocol scores)``.
HEADROOM_PROTOCOLS: dict[str, tuple[str, str]] = {
    "rig_camera_mask": ("camera", "camera"),
    "rig_all_voxels": ("camera", "none"),
    "front_camera_mask": ("camera1", "camera1"),
    "front_all_voxels": ("camera1", "none"),
    "lidar_lidar_mask": ("lidar", "lidar"),
    "lidar_all_voxels": ("lidar", "none"),
}

_NUM_CLASSES = len(OCC3D_CLASSES)


def _scorer() -> Scorer:
    return Scorer(OCC3D_CLASSES, OCC3D_FREE)


def _train_labels(config: SyntheticWorldConfig, scenes: int | None) -> list[Tensor]:
    """Voxel labels of the training split (no sensor is rendered)."""
    out = []
    for s in range(config.train_scenes if scenes is None else min(scenes, config.train_scenes)):
        scene = build_scene(config, "train", s)
        for f in range(config.frames("train")):
            t = f / config.fps
            pose = scene.ego_to_world(t)
            prims = scene.primitives_at(t).transformed(invert_pose(pose))
            out.append(voxel_labels(prims, scene.ground, pose, config.grid, config.label_subsamples))
    return out


def measure(
    config: SyntheticWorldConfig,
    *,
    split: str = "val",
    readouts: Sequence[str] = ("center", "any2", "vote2"),
    masks: Sequence[str] = MASKS,
    ground_shell: float = DEFAULT_GROUND_SHELL,
    depth_stride: int | None = 8,
    train_scenes: int | None = None,
    eval_scenes: int | None = None,
    cache_dir: str | Path | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Floor, ceilings and headroom of ``config``'s ``split`` (see the module docstring).

    Args:
        config: the world.
        split: the evaluated split.
        readouts: :func:`occplug.ceilings.parse_readout` names of the ideal-field readouts.
        masks: a subset of :data:`MASKS`.
        ground_shell: metres of ground below its surface in the ideal field.
        depth_stride: feature stride of the perfect-depth ceiling (None: skip it; it renders the cameras).
        train_scenes, eval_scenes: read only the first scenes (None: all).
        cache_dir: frame cache of the rendered frames the perfect-depth ceiling reads.
        progress: called with a line per scene.

    Returns:
        ``{"world": ..., "frames": n, "floor": {mask: {name: {IoU, mIoU}}}, "ideal": {mask: {readout: ...}},
        "perfect_depth": {mask: {"rig" | "front": ...}}, "lidar_sweep": {mask: ...}, "headroom": {protocol: {counts, shares}},
        "protocol": ...}``, scores in percent.
    """
    bad = sorted(set(masks) - set(MASKS))
    if bad:
        raise ValueError(f"measure: unknown mask '{bad[0]}' (valid: {', '.join(MASKS)})")
    parsed = [parse_readout(r) for r in readouts]
    prior, most = training_prior(_train_labels(config, train_scenes), _NUM_CLASSES, OCC3D_FREE)
    floors: dict[str, Callable[[Tensor], Tensor]] = {
        "all free": lambda lab: torch.full_like(lab, OCC3D_FREE, dtype=torch.long),
        f"all {OCC3D_CLASSES[most]}": lambda lab: torch.full_like(lab, most, dtype=torch.long),
        "per-voxel training prior": lambda lab: prior,
    }
    floor = {m: {name: _scorer() for name in floors} for m in masks}
    sweep = {m: _scorer() for m in masks}
    ideal = {m: {r.name: _scorer() for r in parsed} for m in masks}
    lifts = {m: {"rig": _scorer(), "front": _scorer()} for m in masks} if depth_stride else {}
    headroom = {name: Headroom() for name in HEADROOM_PROTOCOLS}
    rendered = SyntheticDataset(config, split, cache_dir=cache_dir, with_adjacent=False) if depth_stride else None
    frames = config.frames(split)
    n_scenes = config.scenes(split) if eval_scenes is None else min(eval_scenes, config.scenes(split))
    count = 0
    for s in range(n_scenes):
        scene = build_scene(config, split, s)
        seen: dict[str, list[Tensor]] = {m: [] for m in ("camera", "camera1", "lidar", "none")}
        poses = []
        for f in range(frames):
            lab = frame_labels(config, scene, f)
            labels = lab.voxel_labels.long()
            per_mask = {
                "camera": lab.mask_camera,
                "camera1": lab.mask_camera if config.num_cameras == 1 else rig_camera_mask(config, lab.voxel_labels, 1),
                "lidar": lab.mask_lidar,
                "none": torch.ones_like(lab.mask_camera),
            }
            for m, v in per_mask.items():
                seen[m].append(v)
            poses.append(lab.ego_to_world)
            lidar_pred = vote_points(lab.points_ego, lab.point_labels, config.grid, OCC3D_FREE, _NUM_CLASSES)
            for m in masks:
                for name, predict in floors.items():
                    floor[m][name].update(predict(labels), labels, per_mask[m])
                sweep[m].update(lidar_pred, labels, per_mask[m])
            by_k: dict[int, Tensor] = {}
            for r in parsed:
                if r.k not in by_k:
                    by_k[r.k] = scene_field_samples(config, scene, f, r.k, ground_shell=ground_shell)
                pred = read_voxels(by_k[r.k], r.rule, OCC3D_FREE, _NUM_CLASSES)
                for m in masks:
                    ideal[m][r.name].update(pred, labels, per_mask[m])
            if rendered is not None and depth_stride:
                frame = rendered[s * frames + f]
                sem = frame.semantics_2d.long()
                args = (frame.depth, sem, frame.intrinsics, frame.cam_to_ego)
                rig = depth_lift(*args, config.grid, depth_stride, OCC3D_FREE, _NUM_CLASSES)
                front = depth_lift(*(a[:1] for a in args), config.grid, depth_stride, OCC3D_FREE, _NUM_CLASSES)
                for m in masks:
                    lifts[m]["rig"].update(rig, labels, per_mask[m])
                    lifts[m]["front"].update(front, labels, per_mask[m])
            count += 1
        stacked = {m: torch.stack(v) for m, v in seen.items()}
        pose = torch.stack(poses)
        for name, (observe, score) in HEADROOM_PROTOCOLS.items():
            headroom[name].add(history_headroom(stacked[observe], stacked[score], pose, config.grid))
        if progress is not None:
            progress(f"{split} scene {s + 1}/{n_scenes} done")
    return {
        "world": config.to_dict(),
        "split": split,
        "frames": count,
        "ground_shell": ground_shell,
        "depth_stride": depth_stride,
        "floor": {m: {k: v.compute() for k, v in d.items()} for m, d in floor.items()},
        "ideal": {m: {k: v.compute() for k, v in d.items()} for m, d in ideal.items()},
        "perfect_depth": {m: {k: v.compute() for k, v in d.items()} for m, d in lifts.items()},
        "lidar_sweep": {m: v.compute() for m, v in sweep.items()},
        "headroom": {k: {**vars(v), **{f"share_{a}": b for a, b in v.shares().items()}} for k, v in headroom.items()},
    }


def _box_corners(boxes: Tensor) -> Tensor:
    """``(M, 8, 3)`` ego-frame corners of ``(M, >=7)`` boxes ``x, y, z, l, w, h, yaw``."""
    signs = torch.tensor([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=boxes.dtype)
    local = signs[None] * boxes[:, None, 3:6] / 2
    c, s = boxes[:, 6].cos()[:, None], boxes[:, 6].sin()[:, None]
    x = c * local[..., 0] - s * local[..., 1]
    y = s * local[..., 0] + c * local[..., 1]
    return torch.stack([x, y, local[..., 2]], -1) + boxes[:, None, :3]


def object_pixel_heights(
    config: SyntheticWorldConfig, split: str = "val", scenes: int | None = None, max_distance: float | None = None
) -> dict[str, dict[str, float]]:
    """How tall each class's agents appear in the camera that sees them best, per class.

    For every agent within the label grid's range (:func:`~.labels.agent_boxes`) and every camera
    whose image holds the projection of the box's centre (in front of the camera), the box's 8 corners
    are projected and the pixel height is the span of their rows, clipped to the image; an agent
    counts once, in the camera where it is tallest. Occlusion is ignored (an upper bound on what a
    detector sees).

    Returns:
        ``{class name: {count, median_px, p10_px, p90_px, median_distance_m}}``.
    """
    _, intrinsics, cam_to_ego = camera_rig(config.num_cameras, config.image_size)
    h, w = config.image_size
    found: dict[int, list[tuple[float, float]]] = {}
    for s in range(config.scenes(split) if scenes is None else min(scenes, config.scenes(split))):
        scene = build_scene(config, split, s)
        for f in range(config.frames(split)):
            t = f / config.fps
            boxes, labels, _ = agent_boxes(scene.agents, t, scene.ego_to_world(t), config.grid, margin=0.0)
            if boxes.shape[0] == 0:
                continue
            corners = _box_corners(boxes.double())  # (M, 8, 3)
            pts = torch.cat([boxes[:, None, :3].double(), corners], 1).reshape(1, -1, 3)
            n = intrinsics.shape[0]
            uv, depth = project_to_image(pts.expand(n, -1, 3), intrinsics.double(), cam_to_ego.double())
            uv, depth = uv.view(n, -1, 9, 2), depth.view(n, -1, 9)
            centre_in = (depth[..., 0] > 0.1) & (uv[..., 0, 0] >= 0) & (uv[..., 0, 0] < w) & (uv[..., 0, 1] >= 0)
            centre_in &= uv[..., 0, 1] < h
            rows = uv[..., 1:, 1].clamp(0, h)
            height = torch.where(centre_in & (depth[..., 1:] > 0.1).all(-1), rows.amax(-1) - rows.amin(-1), -1.0)
            best = height.amax(0)  # (M,)
            dist = boxes[:, :2].double().norm(dim=-1)
            for m in torch.nonzero(best > 0).squeeze(1).tolist():
                if max_distance is None or float(dist[m]) <= max_distance:
                    found.setdefault(int(labels[m]), []).append((float(best[m]), float(dist[m])))
    out = {}
    for cls in sorted(found):
        px = torch.tensor([p for p, _ in found[cls]], dtype=torch.float64)
        d = torch.tensor([q for _, q in found[cls]], dtype=torch.float64)
        out[OCC3D_CLASSES[cls]] = {
            "count": int(px.numel()),
            "median_px": float(px.median()),
            "p10_px": float(px.quantile(0.1)),
            "p90_px": float(px.quantile(0.9)),
            "median_distance_m": float(d.median()),
        }
    return out
