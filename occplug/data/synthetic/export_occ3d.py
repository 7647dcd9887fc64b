"""The synthetic world written as a nuScenes-shaped tree with Occ3D ground truth.

:func:`write_occ3d_nuscenes` writes what the real data sets ship, so the real readers
(``occplug data prepare nuscenes`` + :class:`~occplug.data.nuscenes.reader.Occ3DNuScenesDataModule`)
can be tested end to end::

    <out>/
      v1.0-trainval/                      the devkit's JSON tables: scene, sample, sample_data, ego_pose,
                                          calibrated_sensor, sensor, sample_annotation, instance, category
                                          (with lidarseg 'index'), attribute, visibility, log, map, lidarseg
      samples/CAM_*/<scene>__<CAM>__<timestamp>.png        8-bit RGB, lossless (nuScenes ships .jpg)
      samples/LIDAR_TOP/<scene>__LIDAR_TOP__<timestamp>.pcd.bin
                                          float32 x, y, z, intensity (0..255), ring index (0) per point
      lidarseg/v1.0-trainval/<sample_data token>_lidarseg.bin   uint8 lidarseg category index per point
      gts/<scene>/<sample token>/labels.npz                    Occ3D: semantics, mask_lidar, mask_camera
      splits.json                         {"train": [scene names], "val": [...], "test": [...]}
      grid.json                           the labels' grid: {"shape", "range", "voxel_size"} (ego frame;
                                          occplug.data.check.GRID_RECORD, read by occplug data check)
      pseudo/                             (optional) pseudo labels, see occplug.data.pseudo_labels:
        depth/<token>/<CAM>.npy, semantics/<token>/<CAM>.png, features/<token>/<CAM>.npy,
        semantics_mapping.yaml; the auxiliary segmenter's semantics_aux/<token>/<CAM>.png and
        semantics_aux_mapping.yaml

Sample tokens are the generated frames' tokens (``synth-0-train-0000-000``); every other token is
an MD5 hex digest of a descriptive name. Timestamps are microseconds (each scene starts at its own
epoch); all sensors of a frame share its timestamp and ego pose. The LiDAR sensor frame is the
synthetic one (x forward, y left, z up, on the roof); points are stored in it. Box velocities are
not stored (nuScenes has none): the reader derives them from the annotation chain as the devkit does,
which is exact for the world's constant-velocity agents except for a box annotated in one sample
only (velocity unknown: 0). Track ids become instance tokens.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from occplug.data.check import write_grid_record
from occplug.data.classes import NUSCENES_LIDARSEG_CATEGORIES as LIDARSEG_CATEGORIES
from occplug.data.classes import OCC3D_TO_NUSCENES as OCC3D_TO_CATEGORY
from occplug.data.frame import Frame
from occplug.data.imageio import write_rgb
from occplug.data.nuscenes.format import write_labels
from occplug.data.nuscenes.index import matrix_to_quaternion

from .config import SPLITS, SyntheticWorldConfig
from .dataset import SyntheticDataset, default_cache_dir
from .pseudo import PseudoRealism, SyntheticPseudoLabels, mapping_table

__all__ = ["OCC3D_TO_CATEGORY", "write_occ3d_nuscenes"]

_LIDAR = "LIDAR_TOP"
_EPOCH = 1_600_000_000_000_000  # µs


def _tok(*parts: object) -> str:
    return hashlib.md5("/".join(str(p) for p in parts).encode()).hexdigest()


def _pose_record(pose: Tensor) -> dict[str, list[float]]:
    p = pose.to(torch.float64).numpy()
    return {"translation": [float(v) for v in p[:3, 3]], "rotation": matrix_to_quaternion(p[:3, :3])}


def _points_in_box(points_ego: np.ndarray, box: np.ndarray) -> int:
    c, (l, w, h), yaw = box[:3], box[3:6], box[6]  # noqa: E741
    d = points_ego - c
    cs, sn = math.cos(yaw), math.sin(yaw)
    x = d[:, 0] * cs + d[:, 1] * sn
    y = -d[:, 0] * sn + d[:, 1] * cs
    return int(((np.abs(x) <= l / 2) & (np.abs(y) <= w / 2) & (np.abs(d[:, 2]) <= h / 2)).sum())


class _Tree:
    def __init__(self, out: Path, version: str) -> None:
        self.out, self.version = out, version
        self.tables: dict[str, list[dict[str, Any]]] = {
            k: []
            for k in (
                "scene",
                "sample",
                "sample_data",
                "ego_pose",
                "calibrated_sensor",
                "sensor",
                "sample_annotation",
                "instance",
                "category",
                "attribute",
                "visibility",
                "log",
                "map",
                "lidarseg",
            )
        }
        self.sensor_token: dict[str, str] = {}
        for name in LIDARSEG_CATEGORIES:
            self.tables["category"].append(
                {
                    "token": _tok("category", name),
                    "name": name,
                    "description": "",
                    "index": LIDARSEG_CATEGORIES.index(name),
                }
            )
        for level, text in enumerate(("v0-40", "v40-60", "v60-80", "v80-100"), start=1):
            self.tables["visibility"].append({"token": str(level), "level": text, "description": f"visibility {text}"})
        self.instances: dict[str, dict[str, Any]] = {}
        self.last_ann: dict[str, dict[str, Any]] = {}

    def sensor(self, channel: str) -> str:
        if channel not in self.sensor_token:
            token = _tok("sensor", channel)
            self.sensor_token[channel] = token
            self.tables["sensor"].append(
                {"token": token, "channel": channel, "modality": "lidar" if channel == _LIDAR else "camera"}
            )
        return self.sensor_token[channel]

    def write_tables(self) -> None:
        folder = self.out / self.version
        folder.mkdir(parents=True, exist_ok=True)
        self.tables["instance"] = list(self.instances.values())
        for name, rows in self.tables.items():
            (folder / f"{name}.json").write_text(json.dumps(rows, indent=0))


def write_occ3d_nuscenes(
    config: SyntheticWorldConfig,
    out: str | Path,
    version: str = "v1.0-trainval",
    splits: Sequence[str] = SPLITS,
    pseudo: str | dict | PseudoRealism | None = None,
    cache_dir: str | Path | None = "default",
    progress: bool = True,
) -> int:
    """Write the world as a nuScenes-shaped tree with Occ3D labels (see the module docstring).

    Args:
        config: the world.
        out: the tree's root (created).
        version: name of the table folder (``v1.0-trainval`` or ``v1.0-mini``).
        splits: which splits to write.
        pseudo: pseudo-label realism (preset name, knob mapping) to also write ``pseudo/``, or None.
        cache_dir: frame cache (``"default"``: the synthetic world's usual cache; None: generate).
        progress: show a progress bar.

    Returns:
        The number of samples written.
    """
    out = Path(out)
    cache = default_cache_dir() if cache_dir == "default" else cache_dir
    tree = _Tree(out, version)
    labeler = None if pseudo is None else SyntheticPseudoLabels(pseudo, taxonomy="occ3d")
    datasets = {s: SyntheticDataset(config, s, cache_dir=cache, with_adjacent=False) for s in splits}
    total = sum(len(d) for d in datasets.values())
    scene_names: dict[str, list[str]] = {s: [] for s in splits}
    written = 0
    with tqdm(total=total, desc="nuScenes-shaped tree", unit="sample", disable=not progress) as bar:
        for split, ds in datasets.items():
            for scene_index in range(ds.num_scenes):
                frames = [ds.frame(scene_index, k) for k in range(ds.frames_per_scene)]
                scene_names[split].append(frames[0].scene)
                _write_scene(tree, frames, len(tree.tables["scene"]), labeler)
                written += len(frames)
                bar.update(len(frames))
    tree.write_tables()
    (out / "splits.json").write_text(json.dumps(scene_names, indent=2))
    write_grid_record(out, config.grid.shape, config.grid.range, config.grid.voxel_size)
    if labeler is not None:
        lacks = labeler.realism.primary_lacks
        (out / "pseudo" / "semantics_mapping.yaml").write_text(
            mapping_table(
                "occ3d", labeler.realism.foreign_taxonomy, primary_lacks=lacks, sky_as_free=labeler.realism.sky_as_free
            )
        )
        if labeler.has_auxiliary:
            (out / "pseudo" / "semantics_aux_mapping.yaml").write_text(
                mapping_table("occ3d", source="auxiliary", primary_lacks=lacks)
            )
    return written


def _write_scene(tree: _Tree, frames: list[Frame], number: int, labeler: SyntheticPseudoLabels | None) -> None:
    t = tree.tables
    first = frames[0]
    name = first.scene
    scene_token, log_token = _tok("scene", name), _tok("log", name)
    t["log"].append(
        {
            "token": log_token,
            "logfile": f"{name}-log",
            "vehicle": "synthetic",
            "date_captured": "2024-01-01",
            "location": "synthetic-town",
        }
    )
    if not t["map"]:
        t["map"].append({"token": _tok("map"), "log_tokens": [], "category": "semantic_prior", "filename": ""})
    t["map"][0]["log_tokens"].append(log_token)
    channels = [*first.camera_names, _LIDAR]
    calib = {}
    for cam, channel in enumerate(first.camera_names):
        calib[channel] = _tok("calibrated_sensor", name, channel)
        t["calibrated_sensor"].append(
            {
                "token": calib[channel],
                "sensor_token": tree.sensor(channel),
                **_pose_record(first.cam_to_ego[cam]),
                "camera_intrinsic": first.intrinsics[cam].double().tolist(),
            }
        )
    calib[_LIDAR] = _tok("calibrated_sensor", name, _LIDAR)
    t["calibrated_sensor"].append(
        {
            "token": calib[_LIDAR],
            "sensor_token": tree.sensor(_LIDAR),
            **_pose_record(first.lidar_to_ego),
            "camera_intrinsic": [],
        }
    )
    epoch = _EPOCH + number * 10**9
    prev_sd: dict[str, str] = {}
    for k, frame in enumerate(frames):
        ts = epoch + round(frame.timestamp * 1e6)
        token = frame.token
        t["sample"].append(
            {
                "token": token,
                "timestamp": ts,
                "scene_token": scene_token,
                "prev": frames[k - 1].token if k else "",
                "next": frames[k + 1].token if k + 1 < len(frames) else "",
            }
        )
        h, w = frame.image_size
        for cam, channel in enumerate(channels):
            sd = _tok("sample_data", token, channel)
            if channel == _LIDAR:
                filename = f"samples/{_LIDAR}/{name}__{_LIDAR}__{ts}.pcd.bin"
                _write_lidar(tree.out, filename, frame, sd, tree.version)
                t["lidarseg"].append(
                    {"token": sd, "sample_data_token": sd, "filename": f"lidarseg/{tree.version}/{sd}_lidarseg.bin"}
                )
            else:
                filename = f"samples/{channel}/{name}__{channel}__{ts}.png"
                write_rgb(tree.out / filename, frame.images[cam])
            t["ego_pose"].append({"token": sd, "timestamp": ts, **_pose_record(frame.ego_to_global)})
            t["sample_data"].append(
                {
                    "token": sd,
                    "sample_token": token,
                    "ego_pose_token": sd,
                    "calibrated_sensor_token": calib[channel],
                    "timestamp": ts,
                    "fileformat": "pcd" if channel == _LIDAR else "png",
                    "is_key_frame": True,
                    "height": 0 if channel == _LIDAR else h,
                    "width": 0 if channel == _LIDAR else w,
                    "filename": filename,
                    "prev": prev_sd.get(channel, ""),
                    "next": "",
                }
            )
            if channel in prev_sd:
                t["sample_data"][-1 - len(channels)]["next"] = sd
            prev_sd[channel] = sd
        _write_annotations(tree, frame, scene_token, token)
        write_labels(
            tree.out / "gts" / name / token / "labels.npz", frame.voxel_labels, frame.mask_lidar, frame.mask_camera
        )
        if labeler is not None:
            labeler.write(frame, tree.out / "pseudo")
    t["scene"].append(
        {
            "token": scene_token,
            "log_token": log_token,
            "nbr_samples": len(frames),
            "first_sample_token": frames[0].token,
            "last_sample_token": frames[-1].token,
            "name": name,
            "description": f"synthetic scene {name}",
        }
    )


def _write_lidar(out: Path, filename: str, frame: Frame, sd: str, version: str) -> None:
    pts = frame.points.numpy().astype(np.float32)
    data = np.zeros((pts.shape[0], 5), dtype=np.float32)
    data[:, :3] = pts[:, :3]
    data[:, 3] = pts[:, 3] * 255.0
    path = out / filename
    path.parent.mkdir(parents=True, exist_ok=True)
    data.reshape(-1).tofile(path)
    lut = np.full(256, 0, dtype=np.uint8)
    for occ, category in OCC3D_TO_CATEGORY.items():
        lut[occ] = LIDARSEG_CATEGORIES.index(category)
    seg = out / "lidarseg" / version / f"{sd}_lidarseg.bin"
    seg.parent.mkdir(parents=True, exist_ok=True)
    lut[frame.point_labels.numpy().clip(0, 255)].astype(np.uint8).tofile(seg)


def _write_annotations(tree: _Tree, frame: Frame, scene_token: str, sample_token: str) -> None:
    if frame.boxes is None or frame.boxes.shape[0] == 0:
        return
    e = frame.ego_to_global.to(torch.float64).numpy()
    points = frame.points_in_ego().double().numpy()
    boxes = frame.boxes.double().numpy()
    for m in range(boxes.shape[0]):
        b = boxes[m]
        track = int(frame.box_track_ids[m])
        label = int(frame.box_labels[m])
        instance = _tok("instance", scene_token, track)
        ann = _tok("sample_annotation", sample_token, track)
        centre = e[:3, :3] @ b[:3] + e[:3, 3]
        c, s = math.cos(b[6]), math.sin(b[6])
        rot = e[:3, :3] @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        record = {
            "token": ann,
            "sample_token": sample_token,
            "instance_token": instance,
            "visibility_token": "4",
            "attribute_tokens": [],
            "translation": centre.tolist(),
            "size": [float(b[4]), float(b[3]), float(b[5])],
            "rotation": matrix_to_quaternion(rot),
            "prev": "",
            "next": "",
            "num_lidar_pts": _points_in_box(points, b),
            "num_radar_pts": 0,
        }
        previous = tree.last_ann.get(instance)
        if previous is not None:
            previous["next"] = ann
            record["prev"] = previous["token"]
        tree.tables["sample_annotation"].append(record)
        tree.last_ann[instance] = record
        inst = tree.instances.setdefault(
            instance,
            {
                "token": instance,
                "category_token": _tok("category", OCC3D_TO_CATEGORY.get(label, "static.other")),
                "nbr_annotations": 0,
                "first_annotation_token": ann,
                "last_annotation_token": ann,
            },
        )
        inst["nbr_annotations"] += 1
        inst["last_annotation_token"] = ann
