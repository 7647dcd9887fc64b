"""Occ3D-nuScenes: the nuScenes sensors with Occ3D occupancy labels, read lazily from a prepared index.

Build the index once::

    occplug data prepare nuscenes --root data/nuscenes --version v1.0-trainval \\
        --occ data/occ3d-nuscenes --out data/nuscenes/occplug_index

then train with the data node switched (``occplug/configs/data/occ3d_nuscenes.yaml`` shows how)::

    occplug fit -c configs/baseline.yaml -c occplug/data/occ3d_nuscenes \\
        data.root=data/nuscenes data.index=data/nuscenes/occplug_index

A frame holds (see :class:`~occplug.data.Frame`): the six cameras (``images`` decoded from the
JPEG/PNG files, ``intrinsics``, ``cam_to_ego`` in the LiDAR keyframe's ego frame, exact for the
ego motion between each camera's and the LiDAR's timestamps), ``ego_to_global`` (the LiDAR
keyframe's ego pose), ``timestamp`` (seconds since the scene's first sample), the ``LIDAR_TOP``
sweep (``points`` in the LiDAR sensor frame, intensity / 255; with ``num_sweeps > 1`` the earlier
sweeps motion-compensated into it and ``extras["point_time_lag"]`` in seconds),
``point_labels`` from nuScenes-lidarseg when present (mapped to Occ3D ids, 255 = noise / ego / no
label), the 3D ``boxes`` with velocities and instance track ids, the Occ3D ``voxel_labels`` with
``mask_lidar`` and ``mask_camera``, and ``sequence_lidar_origins`` (every sample of the scene).
The official train/val split is by scene; ``predict`` reads ``val``.

Readers are lazy: the index is read once; each item opens only its own files. LiDAR files
(keyframe, sweeps, lidarseg) are opened only when points are loaded: ``load_points: true``, or the
default ``null`` (auto) when the model declares that it reads ``points`` / ``point_labels``
(:meth:`~occplug.data.datamodule.OccDataModule.require_fields`; the runner calls it). A camera-only
run thus opens no ``LIDAR_TOP`` file, and a tree without them trains and evaluates.
"""

from __future__ import annotations

from collections.abc import Collection
from pathlib import Path
from typing import Annotated, ClassVar

import numpy as np
import torch
from torch.utils.data import Dataset

from occplug.constraints import Fraction, Length, NonNegative, Positive
from occplug.context import ComponentBuilder
from occplug.geometry import GridSpec

from ..classes import OCC3D_CLASSES, OCC3D_FREE, nuscenes_to_occ3d
from ..formats import FormatError
from ..frame import Frame
from ..imageio import read_rgb
from ..pipeline import FramePipeline, ReaderDataModule, ReaderDataset, resolve_load_points, stat_files
from ..sequences import SceneIndex
from .format import OCC3D_GRID, read_labels
from .index import NuScenesIndex, read_index

__all__ = ["Occ3DNuScenesDataModule", "Occ3DNuScenesDataset", "read_pcd_bin"]

_POINT_DIMS = 5  # nuScenes .pcd.bin: x, y, z, intensity, ring index (float32)


def read_pcd_bin(path: str | Path) -> np.ndarray:
    """A nuScenes ``.pcd.bin`` as ``(P, 5)`` float32 (x, y, z, intensity 0..255, ring).

    Raises:
        FormatError: a missing file or a length that is not a whole number of 5-float points.
    """
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: no such LiDAR file")
    size = path.stat().st_size
    if size % (4 * _POINT_DIMS):
        raise FormatError(f"{path}: {size} bytes is not a whole number of {_POINT_DIMS}-float32 points (corrupt .bin?)")
    return np.fromfile(path, dtype=np.float32).reshape(-1, _POINT_DIMS)


def _pcd_size_problem(size: int) -> str | None:
    return (
        None
        if size % (4 * _POINT_DIMS) == 0
        else f"{size} bytes is not a whole number of {_POINT_DIMS}-float32 points (corrupt .bin?)"
    )


class Occ3DNuScenesDataset(ReaderDataset):
    """One split of an Occ3D-nuScenes index (see the module docstring for the frame's fields).

    Args:
        index: the prepared index.
        split: ``train``, ``val``, ``test`` or ``predict`` (= ``val``).
        root: the nuScenes root the index's paths are relative to.
        occ_root: the Occ3D root, or None for no voxel labels.
        cameras: camera channels to load, in order.
        grid: the label grid; every ``labels.npz`` must have its shape.
        num_sweeps: LiDAR sweeps per frame (1 = the keyframe only).
        load_points: read LiDAR points (and lidarseg labels).
        min_box_points: drop boxes with fewer annotated LiDAR points.
        offsets, pipeline, cache_dir: see :class:`~occplug.data.pipeline.ReaderDataset`.
    """

    def __init__(
        self,
        index: NuScenesIndex,
        split: str,
        root: Path,
        occ_root: Path | None,
        cameras: tuple[str, ...],
        grid: GridSpec,
        num_sweeps: int = 1,
        load_points: bool = True,
        min_box_points: int = 0,
        offsets: tuple[int, ...] = (),
        pipeline: FramePipeline | None = None,
        cache_dir: str | None = None,
    ) -> None:
        self.index = index
        self.split = "val" if split == "predict" else split
        self.items = index.split_indices(self.split)
        samples = index.samples
        super().__init__(
            SceneIndex.from_scene_names([samples[i]["scene"] for i in self.items]),
            offsets,
            pipeline,
            cache_dir,
            cache_key={
                "reader": "occ3d_nuscenes",
                "index": str(index.path),
                "mtime": index.path.stat().st_mtime,
                "cameras": cameras,
                "grid": grid.to_dict(),
                "sweeps": num_sweeps,
                "points": load_points,
                "occ": str(occ_root),
                "min_box_points": min_box_points,
            },
        )
        self.root, self.occ_root = root, occ_root
        self.camera_ids = [index.cameras.index(c) for c in cameras]
        self.cameras = tuple(cameras)
        self.grid = grid
        self.num_sweeps = num_sweeps
        self.load_points = load_points
        self.min_box_points = min_box_points
        seg_names = index.meta.get("lidarseg_categories") or []
        self._seg_lut = np.full(256, 255, dtype=np.int64)
        for i, name in enumerate(seg_names[:256]):
            self._seg_lut[i] = nuscenes_to_occ3d(name)

    def token(self, index: int) -> str:
        return self.index.samples[self.items[index]]["token"]

    def files(self) -> list[Path]:
        """The images and ``labels.npz`` files items read, for :func:`stat_files` (LiDAR files: :meth:`lidar_files`)."""
        out: list[Path] = []
        for s in self.items:
            rec = self.index.samples[s]
            out.extend(self.root / rec["cams"][c] for c in self.camera_ids)
            if self.occ_root is not None and rec.get("occ"):
                out.append(self.occ_root / rec["occ"])
        return out

    def lidar_files(self) -> list:
        """The LiDAR files items read when points are loaded: the keyframe and its ``num_sweeps - 1`` sweeps
        (``(path, size check)`` pairs) and the lidarseg file, for :func:`stat_files`."""
        out: list = []
        for s in self.items:
            rec = self.index.samples[s]
            out.append((self.root / rec["lidar"], _pcd_size_problem))
            if rec.get("lidarseg"):
                out.append(self.root / rec["lidarseg"])
            out.extend((self.root / rel, _pcd_size_problem) for rel in rec["sweeps"][: max(0, self.num_sweeps - 1)])
        return out

    def load(self, index: int) -> Frame:
        """Decode item ``index`` (see the module docstring)."""
        s = self.items[index]
        rec = self.index.samples[s]
        a = self.index.arrays
        images = [read_rgb(self.root / rec["cams"][c]) for c in self.camera_ids]
        shapes = {tuple(img.shape) for img in images}
        if len(shapes) > 1:
            raise FormatError(
                f"{self.root / rec['cams'][self.camera_ids[0]]}: the cameras of sample {rec['token']} have "
                f"different image sizes {sorted(shapes)}; set image_size to resize them"
            )
        ego = torch.from_numpy(a["ego_to_global"][s].copy())
        lidar_to_ego = torch.from_numpy(a["lidar_to_ego"][s]).float()
        frame = Frame(
            images=torch.stack(images),
            intrinsics=torch.from_numpy(a["intrinsics"][s][self.camera_ids]).float(),
            cam_to_ego=torch.from_numpy(a["cam_to_ego"][s][self.camera_ids]).float(),
            img_aug=torch.eye(3).expand(len(images), 3, 3).clone(),
            ego_to_global=ego,
            timestamp=float(a["timestamp"][s] - a["scene_start"][s]) / 1e6,
            scene=rec["scene"],
            frame_index=int(rec["frame_index"]),
            token=rec["token"],
            camera_names=self.cameras,
            lidar_to_ego=lidar_to_ego,
            extras={"split": self.split},
        )
        if self.load_points:
            self._points(frame, s, rec)
        if self.occ_root is not None and rec.get("occ"):
            labels = read_labels(self.occ_root / rec["occ"], expected_shape=self.grid.shape)
            frame.voxel_labels, frame.mask_lidar, frame.mask_camera = (
                labels.semantics,
                labels.mask_lidar,
                labels.mask_camera,
            )
        b0, b1 = int(a["box_offsets"][s]), int(a["box_offsets"][s + 1])
        keep = np.arange(b0, b1)
        if self.min_box_points > 0:
            keep = keep[a["box_num_lidar_pts"][b0:b1] >= self.min_box_points]
        frame.boxes = torch.from_numpy(a["boxes"][keep]).float()
        frame.box_labels = torch.from_numpy(a["box_labels"][keep].astype(np.int64))
        frame.box_track_ids = torch.from_numpy(a["box_track_ids"][keep].astype(np.int64))
        frame.sequence_lidar_origins = torch.from_numpy(self.index.sequence_lidar_origins(s)).float()
        return frame

    def _points(self, frame: Frame, s: int, rec: dict) -> None:
        a = self.index.arrays
        raw = read_pcd_bin(self.root / rec["lidar"])
        parts = [raw[:, :4]]
        lags = [np.zeros(raw.shape[0], dtype=np.float32)]
        labels = None
        if rec.get("lidarseg"):
            path = self.root / rec["lidarseg"]
            if not path.is_file():
                raise FormatError(f"{path}: no such lidarseg file")
            seg = np.fromfile(path, dtype=np.uint8)
            if seg.shape[0] != raw.shape[0]:
                raise FormatError(
                    f"{path}: {seg.shape[0]} labels for {raw.shape[0]} points in {self.root / rec['lidar']}"
                )
            labels = [self._seg_lut[seg]]
        q0 = int(a["sweep_offsets"][s])
        for q, rel in enumerate(rec["sweeps"][: max(0, self.num_sweeps - 1)]):
            sweep = read_pcd_bin(self.root / rel)
            m = a["sweep_to_lidar"][q0 + q]
            xyz = sweep[:, :3].astype(np.float64) @ m[:3, :3].T + m[:3, 3]
            parts.append(np.concatenate([xyz.astype(np.float32), sweep[:, 3:4]], 1))
            lags.append(np.full(sweep.shape[0], a["sweep_time_lag"][q0 + q], dtype=np.float32))
            if labels is not None:
                labels.append(np.full(sweep.shape[0], 255, dtype=np.int64))
        pts = np.concatenate(parts, 0)
        pts[:, 3] = pts[:, 3] / 255.0
        frame.points = torch.from_numpy(pts)
        if labels is not None:
            frame.point_labels = torch.from_numpy(np.concatenate(labels))
        if len(parts) > 1:
            frame.extras["point_time_lag"] = torch.from_numpy(np.concatenate(lags))


class Occ3DNuScenesDataModule(ReaderDataModule):
    """Occ3D-nuScenes (nuScenes sensors + Occ3D occupancy) from a prepared index, registered as data ``occ3d_nuscenes``.

    Args:
        root: the nuScenes data root (``samples/``, ``sweeps/``, ``lidarseg/``); overrides the one in the index.
        index: the index ``occplug data prepare nuscenes --out`` wrote (its folder or the ``.npz``).
        occ_root: the Occ3D folder (holding ``gts/``); default: the one recorded in the index.
        grid: the label grid (default Occ3D's ``[-40, -40, -1, 40, 40, 5.4]`` at 0.4 m); every
            ``labels.npz`` must have its shape.
        cameras: camera channels to load, in order (default all six).
        image_size: ``[H, W]`` the images are resized to (all splits), e.g. ``[256, 704]``.
        num_sweeps: LiDAR sweeps per frame (1 = keyframe only; up to the number ``prepare`` recorded + 1).
        load_points: read LiDAR points and lidarseg labels: true, false (opens no LiDAR file), or null
            (default, auto): iff the model reads ``points`` or ``point_labels`` (see
            :meth:`~occplug.data.datamodule.OccDataModule.require_fields`; loaded when undeclared).
        load_occupancy: read the Occ3D labels.
        min_box_points: drop boxes with fewer LiDAR points (nuScenes ``num_lidar_pts``).
        adjacent_offsets: sample offsets loaded into ``Frame.adjacent`` (e.g. ``[-1, 1]``).
        sequential: read scenes in temporal order (:mod:`occplug.data.sequences`; or ``{run_length: N}``).
        augment: training augmentation (:mod:`occplug.data.augment`).
        pseudo_labels: file-based pseudo labels (:mod:`occplug.data.pseudo_labels`).
        registry: the registry ``label_sources`` and ``transforms`` are built from (the builder hands it in).
        label_sources, transforms, fields: plugins' label sources, frame transforms and field collate rules
            (:mod:`occplug.data.extensions`).
        batch_size: samples per batch on each device.
        num_workers: loader worker processes.
        pin_memory: pin batches in memory (for GPU training).
        cache_dir: cache decoded frames on disk here, or None.
        check_files: at construction, check that every image and ``labels.npz`` of every split exists
            and that the first ``labels.npz`` has the grid's shape (any later one with another shape
            fails when it is read), so a bad tree fails in one line. LiDAR files (keyframes, the sweeps
            used, lidarseg; sizes of ``.pcd.bin``) are checked then with ``load_points: true``, and with
            auto when :meth:`require_fields` declares points.
    """

    #: the label names, index = id (config validation reads them before anything is built)
    class_names: ClassVar[tuple[str, ...]] = OCC3D_CLASSES

    def __init__(
        self,
        root: str,
        index: str,
        occ_root: str | None = None,
        grid: dict | None = None,
        cameras: list[str] | None = None,
        image_size: Annotated[list[Annotated[int, Positive]] | None, Length(exact=2)] = None,
        num_sweeps: Annotated[int, Positive] = 1,
        load_points: bool | None = None,
        load_occupancy: bool = True,
        min_box_points: Annotated[int, NonNegative] = 0,
        adjacent_offsets: list[int] | None = None,
        sequential: bool | dict = False,
        augment: str | dict | None = None,
        pseudo_labels: dict | None = None,
        batch_size: Annotated[int, Positive] = 1,
        num_workers: Annotated[int, NonNegative] = 0,
        pin_memory: bool = False,
        cache_dir: str | None = None,
        check_files: bool = True,
        label_sources: dict | None = None,
        registry: ComponentBuilder | None = None,
        transforms: list | None = None,
        fields: dict | None = None,
        label_fraction: Annotated[float, Fraction] = 1.0,
        subset: str = "all",
    ) -> None:
        super().__init__(
            grid=grid if grid is not None else OCC3D_GRID,
            class_names=self.class_names,
            free_label=OCC3D_FREE,
            ignore_label=255,
            batch_size=batch_size,
            num_workers=num_workers,
            pin_memory=pin_memory,
            image_size=image_size,
            adjacent_offsets=adjacent_offsets,
            sequential=sequential,
            augment=augment,
            pseudo_labels=pseudo_labels,
            cache_dir=cache_dir,
            label_sources=label_sources,
            registry=registry,
            transforms=transforms,
            fields=fields,
            label_fraction=label_fraction,
            subset=subset,
        )
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"data.root: {self.root} is not a folder (the nuScenes data root)")
        self.index = read_index(index)
        recorded = self.index.meta.get("occ_root")
        occ = occ_root if occ_root is not None else recorded
        self.occ_root = Path(occ) if occ is not None and load_occupancy else None
        if self.occ_root is not None and not self.occ_root.is_dir():
            raise FileNotFoundError(f"data.occ_root: {self.occ_root} is not a folder (the Occ3D-nuScenes labels)")
        available = self.index.cameras
        self.cameras = tuple(cameras) if cameras else available
        for cam in self.cameras:
            if cam not in available:
                raise ValueError(f"data.cameras: '{cam}' is not in the index (cameras: {', '.join(available)})")
        if num_sweeps < 1:
            raise ValueError(f"data.num_sweeps must be >= 1, got {num_sweeps}")
        self.num_sweeps = num_sweeps
        if load_points not in (None, True, False):
            raise ValueError(f"data.load_points must be true, false or null (auto), got {load_points!r}")
        self.load_points = load_points
        self.min_box_points = min_box_points
        self.check_files = check_files
        if check_files:
            for split in ("train", "val", "test"):
                ds = self.build_dataset(split)
                assert isinstance(ds, Occ3DNuScenesDataset)
                stat_files(ds.files())
                if load_points:
                    stat_files(ds.lidar_files())
                if len(ds) and ds.occ_root is not None and self.index.samples[ds.items[0]].get("occ"):
                    read_labels(ds.occ_root / self.index.samples[ds.items[0]]["occ"], expected_shape=self.grid.shape)

    @property
    def reads_points(self) -> bool:
        """Whether items open LiDAR files (``load_points``, resolved against the declared fields)."""
        return resolve_load_points(self.load_points, self.required_fields)

    def require_fields(self, fields: Collection[str]) -> None:
        """See :meth:`OccDataModule.require_fields`; with ``load_points`` auto and points declared, checks
        every LiDAR file of every split now (keyframes, the sweeps used, lidarseg)."""
        super().require_fields(fields)
        if self.reads_points and self.load_points is None and self.check_files:
            for split in ("train", "val", "test"):
                ds = self.build_dataset(split)
                assert isinstance(ds, Occ3DNuScenesDataset)
                stat_files(ds.lidar_files())

    def build_dataset(self, split: str) -> Dataset[Frame]:
        """The :class:`Occ3DNuScenesDataset` of ``split`` (``predict`` = ``val``)."""
        return Occ3DNuScenesDataset(
            self.index,
            split,
            self.root,
            self.occ_root,
            self.cameras,
            self.grid,
            self.num_sweeps,
            self.reads_points,
            self.min_box_points,
            self.adjacent_offsets,
            self.pipeline(split),
            self.cache_dir,
        )
