"""SemanticKITTI semantic scene completion: the left camera, the LiDAR and the SSC voxel labels.

Reads ``<root>/sequences/<XX>/`` as distributed (``image_2/``, ``velodyne/*.bin``,
``labels/*.label``, ``voxels/*.{label,invalid}``, ``calib.txt``, ``poses.txt``, ``times.txt``).
The samples of a sequence are its labelled scans (those with ``voxels/<NNNNNN>.label``: every 5th
scan, so 2 Hz); a sequence without voxel labels (the test sequences 11-21) contributes every 5th
scan of ``image_2/``. Standard split: train 00-07, 09, 10; val 08; test 11-21 (``predict`` reads val).

**Frames of reference.** The ego frame of a SemanticKITTI frame is the **velodyne frame** of its scan
(x forward, y left, z up): the SSC grid ``[0, -25.6, -2, 51.2, 25.6, 4.4]`` at 0.2 m (256 x 256 x 32)
is defined there, so ``voxel_labels`` need no resampling and ``lidar_to_ego`` is the identity.
``cam_to_ego`` places the left colour camera (``image_2``: ``K`` = ``P2[:, :3]``, its offset from
the rectified cam0 ``K^-1 P2[:, 3]``, and ``Tr`` velodyne -> cam0); ``ego_to_global`` is
``poses[scan] @ Tr``, i.e. the global frame is the sequence's first cam0 frame.

A frame holds ``images`` ``(1, 3, H, W)`` (KITTI image sizes differ slightly between sequences:
set ``image_size`` to batch them), ``points`` (x, y, z, reflectance), ``point_labels`` (the 20 SSC
classes through the learning map; 255 = unlabelled / ignored), ``voxel_labels`` (``.label`` through
the completion learning map: 0 empty, 1-19 classes, 255 ignored) and ``voxel_invalid`` (``.invalid``),
``sequence_lidar_origins`` (every sample of the sequence), ``timestamp`` (``times.txt``),
``frame_index`` (position among the sequence's samples) and ``extras["scan"]`` (the scan number).
There are no boxes and no Occ3D-style visibility masks.
"""

from __future__ import annotations

from collections.abc import Collection
from functools import partial
from pathlib import Path
from typing import Annotated, ClassVar

import numpy as np
import torch
from torch.utils.data import Dataset

from occplug.constraints import Fraction, Length, NonNegative, Positive
from occplug.context import ComponentBuilder
from occplug.geometry import GridSpec

from ..classes import SEMANTIC_KITTI_CLASSES
from ..formats import FormatError
from ..frame import Frame
from ..imageio import read_rgb
from ..pipeline import FramePipeline, ReaderDataModule, ReaderDataset, latest_mtime, resolve_load_points, stat_files
from ..sequences import SceneIndex
from .format import IGNORE, SPLIT_SEQUENCES, SSC_GRID, learning_map_lut, read_voxels, sample_token, voxel_file_problem

__all__ = ["SemanticKITTIDataModule", "SemanticKITTIDataset", "read_calib", "read_poses", "read_velodyne"]


def read_calib(path: Path) -> dict[str, np.ndarray]:
    """``calib.txt``: ``{"P0".."P3": (3, 4), "Tr": (4, 4)}`` float64."""
    if not path.is_file():
        raise FormatError(f"{path}: no such calibration file")
    out: dict[str, np.ndarray] = {}
    for line in path.read_text().splitlines():
        key, sep, values = line.partition(":")
        if not sep:
            continue
        try:
            nums = np.array([float(v) for v in values.split()], dtype=np.float64)
        except ValueError:
            raise FormatError(f"{path}: line '{key}' holds a value that is not a number") from None
        if nums.size != 12:
            raise FormatError(f"{path}: '{key}' has {nums.size} numbers; expected 12 (a 3 x 4 matrix)")
        out[key.strip()] = nums.reshape(3, 4)
    for key in ("P2", "Tr"):
        if key not in out:
            raise FormatError(f"{path}: no '{key}' line")
    tr = np.eye(4)
    tr[:3] = out["Tr"]
    out["Tr"] = tr
    return out


def read_poses(path: Path) -> np.ndarray:
    """``poses.txt``: ``(S, 4, 4)`` float64, one per scan."""
    if not path.is_file():
        raise FormatError(f"{path}: no such poses file")
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            nums = [float(v) for v in line.split()]
        except ValueError:
            raise FormatError(f"{path}: line {n} holds a value that is not a number") from None
        if len(nums) != 12:
            raise FormatError(f"{path}: line {n} has {len(nums)} numbers; expected 12 (a 3 x 4 pose)")
        pose = np.eye(4)
        pose[:3] = np.asarray(nums).reshape(3, 4)
        rows.append(pose)
    return np.asarray(rows).reshape(-1, 4, 4)


def read_velodyne(path: Path) -> np.ndarray:
    """A velodyne ``.bin`` as ``(P, 4)`` float32 (x, y, z, reflectance).

    Raises:
        FormatError: a missing file or a length that is not a whole number of 4-float points.
    """
    if not path.is_file():
        raise FormatError(f"{path}: no such velodyne file")
    size = path.stat().st_size
    if size % 16:
        raise FormatError(f"{path}: {size} bytes is not a whole number of 4-float32 points (corrupt .bin?)")
    return np.fromfile(path, dtype=np.float32).reshape(-1, 4)


def _velodyne_problem(size: int) -> str | None:
    return None if size % 16 == 0 else f"{size} bytes is not a whole number of 4-float32 points (corrupt .bin?)"


def _point_lut() -> np.ndarray:
    lut = learning_map_lut(completion=False).astype(np.int64)
    lut[lut == 0] = IGNORE  # a point is never "empty": unlabelled / outliers are ignored
    return lut


class _Sequence:
    """One sequence's calibration, poses, times and sample scans."""

    def __init__(self, root: Path, name: str, with_labels: bool) -> None:
        self.name = name
        self.folder = root / "sequences" / name
        if not self.folder.is_dir():
            raise FileNotFoundError(f"{self.folder}: no such sequence folder")
        calib = read_calib(self.folder / "calib.txt")
        p2, tr = calib["P2"], calib["Tr"]
        k = p2[:, :3]
        cam2_from_cam0 = np.eye(4)
        cam2_from_cam0[:3, 3] = np.linalg.solve(k, p2[:, 3])
        velo_to_cam2 = cam2_from_cam0 @ tr
        self.intrinsics = k
        self.cam_to_velo = np.linalg.inv(velo_to_cam2)
        self.tr = tr
        self.poses = read_poses(self.folder / "poses.txt")
        times = self.folder / "times.txt"
        self.times = np.loadtxt(times, dtype=np.float64, ndmin=1) if times.is_file() else None
        labelled = sorted(self.folder.glob("voxels/*.label"))
        if labelled:
            self.scans = [int(p.stem) for p in labelled]
            self.labelled = True
        else:
            images = sorted(self.folder.glob("image_2/*.png"))
            self.scans = [int(p.stem) for p in images if int(p.stem) % 5 == 0]
            self.labelled = False
        if with_labels and not self.labelled:
            raise FormatError(f"{self.folder / 'voxels'}: no voxel labels (*.label) in this sequence")
        for scan in self.scans:
            if scan >= len(self.poses):
                raise FormatError(
                    f"{self.folder / 'poses.txt'}: {len(self.poses)} poses, but scan {scan:06d} needs line {scan + 1}"
                )

    def ego_to_global(self, scan: int) -> np.ndarray:
        return self.poses[scan] @ self.tr

    def time(self, scan: int) -> float:
        if self.times is not None and scan < len(self.times):
            return float(self.times[scan])
        return scan / 10.0


class SemanticKITTIDataset(ReaderDataset):
    """One split of SemanticKITTI SSC (see the module docstring).

    Args:
        root: the folder holding ``sequences/``.
        split: ``train``, ``val``, ``test`` or ``predict`` (= ``val``).
        sequences: the split's sequences; those without a folder are left out (:attr:`missing`), but
            a non-empty list of which none is present is an error.
        grid: the voxel grid (velodyne frame); voxel files must have its shape.
        load_points: read velodyne scans and point labels.
        offsets, pipeline, cache_dir: see :class:`~occplug.data.pipeline.ReaderDataset`; the cache
            key holds the newest modification time of the files items read, so a rewritten tree is
            decoded again.

    Raises:
        FormatError: none of ``sequences`` is present (one line naming the first expected folder).
    """

    def __init__(
        self,
        root: Path,
        split: str,
        sequences: tuple[str, ...],
        grid: GridSpec,
        load_points: bool = True,
        offsets: tuple[int, ...] = (),
        pipeline: FramePipeline | None = None,
        cache_dir: str | None = None,
    ) -> None:
        self.root = root
        self.split = "val" if split == "predict" else split
        self.grid = grid
        self.load_points = load_points
        present = [s for s in sequences if (root / "sequences" / s).is_dir()]
        #: The split's sequences without a folder under ``sequences/``.
        self.missing = [s for s in sequences if s not in present]
        if sequences and not present:
            raise FormatError(
                f"{root / 'sequences' / sequences[0]}: no such sequence folder (none of the {self.split} "
                f"sequences {', '.join(sequences)} is present)"
            )
        self.sequences = [_Sequence(root, s, with_labels=False) for s in present]
        self.items = [(seq, pos, scan) for seq in self.sequences for pos, scan in enumerate(seq.scans)]
        key: dict = {
            "reader": "semantickitti",
            "root": str(root.resolve()),
            "split": self.split,
            "grid": grid.to_dict(),
            "points": load_points,
        }
        if cache_dir is not None:
            own = [seq.folder / name for seq in self.sequences for name in ("calib.txt", "poses.txt", "times.txt")]
            key["mtime"] = latest_mtime([*own, *self.files(), *(self.lidar_files() if load_points else [])])
        super().__init__(
            SceneIndex.from_scene_names([seq.name for seq, _, _ in self.items]),
            offsets,
            pipeline,
            cache_dir,
            cache_key=key,
        )
        self._point_lut = _point_lut()

    def token(self, index: int) -> str:
        seq, _, scan = self.items[index]
        return sample_token(seq.name, scan)

    def files(self) -> list:
        """The images and voxel files items read (``(path, size check)`` pairs for voxel files), for
        :func:`stat_files` (LiDAR files: :meth:`lidar_files`)."""
        out: list = []
        label_size = partial(voxel_file_problem, ".label", shape=self.grid.shape)
        bits_size = partial(voxel_file_problem, ".invalid", shape=self.grid.shape)
        for seq, _, scan in self.items:
            name = f"{scan:06d}"
            out.append(seq.folder / "image_2" / f"{name}.png")
            if seq.labelled:
                out.append((seq.folder / "voxels" / f"{name}.label", label_size))
                out.append((seq.folder / "voxels" / f"{name}.invalid", bits_size))
        return out

    def lidar_files(self) -> list:
        """The LiDAR files items read when points are loaded: ``velodyne/*.bin`` (with a size check) and, in
        labelled sequences, ``labels/*.label``, for :func:`stat_files`."""
        out: list = []
        for seq, _, scan in self.items:
            name = f"{scan:06d}"
            out.append((seq.folder / "velodyne" / f"{name}.bin", _velodyne_problem))
            if seq.labelled:
                out.append(seq.folder / "labels" / f"{name}.label")
        return out

    def load(self, index: int) -> Frame:
        """Decode item ``index`` (see the module docstring)."""
        seq, pos, scan = self.items[index]
        name = f"{scan:06d}"
        image = read_rgb(seq.folder / "image_2" / f"{name}.png")
        ego = seq.ego_to_global(scan)
        frame = Frame(
            images=image[None],
            intrinsics=torch.from_numpy(seq.intrinsics).float()[None],
            cam_to_ego=torch.from_numpy(seq.cam_to_velo).float()[None],
            img_aug=torch.eye(3)[None],
            ego_to_global=torch.from_numpy(ego.copy()),
            timestamp=seq.time(scan),
            scene=seq.name,
            frame_index=pos,
            token=sample_token(seq.name, scan),
            camera_names=("image_2",),
            lidar_to_ego=torch.eye(4),
            extras={"split": self.split, "scan": scan},
        )
        if self.load_points:
            pts = read_velodyne(seq.folder / "velodyne" / f"{name}.bin")
            frame.points = torch.from_numpy(pts.copy())
            label_path = seq.folder / "labels" / f"{name}.label"
            if label_path.is_file():
                raw = np.fromfile(label_path, dtype=np.uint32)
                if raw.shape[0] != pts.shape[0]:
                    raise FormatError(
                        f"{label_path}: {raw.shape[0]} labels for {pts.shape[0]} points in "
                        f"{seq.folder / 'velodyne' / (name + '.bin')}"
                    )
                frame.point_labels = torch.from_numpy(self._point_lut[raw & 0xFFFF])
        if seq.labelled:
            vox = read_voxels(seq.folder / "voxels" / f"{name}.label", self.grid.shape)
            frame.voxel_labels, frame.voxel_invalid = vox.labels, vox.invalid
        origins = np.stack([seq.ego_to_global(s)[:3, 3] for s in seq.scans])
        frame.sequence_lidar_origins = torch.from_numpy((origins - ego[:3, 3]) @ ego[:3, :3]).float()
        return frame


class SemanticKITTIDataModule(ReaderDataModule):
    """SemanticKITTI semantic scene completion (left camera, LiDAR, SSC voxels), registered as data ``semantickitti``.

    Args:
        root: the folder holding ``sequences/`` (SemanticKITTI's ``dataset/``).
        grid: the voxel grid in the velodyne frame (default the SSC grid, 256 x 256 x 32 at 0.2 m).
        splits: ``{split: [sequence names]}`` replacing the standard split (train 00-07, 09, 10; val 08; test 11-21).
        image_size: ``[H, W]`` the images are resized to (all splits), e.g. ``[370, 1220]``.
        load_points: read velodyne scans and point labels: true, false (opens no LiDAR file), or null
            (default, auto): iff the model reads ``points`` or ``point_labels`` (see
            :meth:`~occplug.data.datamodule.OccDataModule.require_fields`; loaded when undeclared).
        adjacent_offsets: sample offsets loaded into ``Frame.adjacent`` (labelled scans, 0.5 s apart).
        sequential: read sequences in temporal order (:mod:`occplug.data.sequences`; or ``{run_length: N}``).
        augment: training augmentation (:mod:`occplug.data.augment`; mirror with ``bev.flip_y``: the grid is
            not symmetric in x).
        pseudo_labels: file-based pseudo labels (:mod:`occplug.data.pseudo_labels`; camera name ``image_2``).
        registry: the registry ``label_sources`` and ``transforms`` are built from (the builder hands it in).
        label_sources, transforms, fields: plugins' label sources, frame transforms and field collate rules
            (:mod:`occplug.data.extensions`).
        batch_size: samples per batch on each device.
        num_workers: loader worker processes.
        pin_memory: pin batches in memory (for GPU training).
        cache_dir: cache decoded frames on disk here, or None.
        check_files: at construction, check every image and voxel file of every split (existence,
            sizes), so a bad tree fails in one line; LiDAR files (``velodyne/`` with sizes, ``labels/``)
            then with ``load_points: true``, and with auto when :meth:`require_fields` declares points.
            The train and val splits need at least one of their sequences (missing ones are left out;
            ``occplug data check semantickitti`` lists them); a test split none of whose sequences is
            present fails only when it is read.
    """

    #: the label names, index = id (config validation reads them before anything is built)
    class_names: ClassVar[tuple[str, ...]] = SEMANTIC_KITTI_CLASSES

    def __init__(
        self,
        root: str,
        grid: dict | None = None,
        splits: dict[str, list[str]] | None = None,
        image_size: Annotated[list[Annotated[int, Positive]] | None, Length(exact=2)] = None,
        load_points: bool | None = None,
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
            grid=grid if grid is not None else SSC_GRID,
            class_names=self.class_names,
            free_label=0,
            ignore_label=IGNORE,
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
        if not (self.root / "sequences").is_dir():
            raise FileNotFoundError(
                f"data.root: {self.root / 'sequences'} is not a folder (SemanticKITTI's dataset/ root)"
            )
        self.splits = dict(SPLIT_SEQUENCES)
        for split, seqs in (splits or {}).items():
            if split not in ("train", "val", "test"):
                raise ValueError(f"data.splits.{split}: unknown split (valid: train, val, test)")
            self.splits[split] = tuple(f"{int(s):02d}" if str(s).isdigit() else str(s) for s in seqs)
        if load_points not in (None, True, False):
            raise ValueError(f"data.load_points must be true, false or null (auto), got {load_points!r}")
        self.load_points = load_points
        self.check_files = check_files
        if check_files:
            for ds in self._checked_datasets():
                if ds.split in ("train", "val"):
                    for seq in ds.sequences:
                        if not seq.labelled:
                            raise FormatError(
                                f"{seq.folder / 'voxels'}: no voxel labels (*.label) in {ds.split} sequence {seq.name}"
                            )
                stat_files(ds.files())
                if load_points:
                    stat_files(ds.lidar_files())

    def _checked_datasets(self) -> list[SemanticKITTIDataset]:
        """The datasets the file checks cover: train, val, and test when any of its sequences is present."""
        out = []
        for split in ("train", "val", "test"):
            if split == "test" and not any((self.root / "sequences" / s).is_dir() for s in self.splits["test"]):
                continue
            ds = self.build_dataset(split)
            assert isinstance(ds, SemanticKITTIDataset)
            out.append(ds)
        return out

    @property
    def reads_points(self) -> bool:
        """Whether items open LiDAR files (``load_points``, resolved against the declared fields)."""
        return resolve_load_points(self.load_points, self.required_fields)

    def require_fields(self, fields: Collection[str]) -> None:
        """See :meth:`OccDataModule.require_fields`; with ``load_points`` auto and points declared, checks
        every ``velodyne/`` and ``labels/`` file now."""
        super().require_fields(fields)
        if self.reads_points and self.load_points is None and self.check_files:
            for ds in self._checked_datasets():
                stat_files(ds.lidar_files())

    def build_dataset(self, split: str) -> Dataset[Frame]:
        """The :class:`SemanticKITTIDataset` of ``split`` (``predict`` = ``val``)."""
        key = "val" if split == "predict" else split
        return SemanticKITTIDataset(
            self.root,
            split,
            self.splits[key],
            self.grid,
            self.reads_points,
            self.adjacent_offsets,
            self.pipeline(split),
            self.cache_dir,
        )
