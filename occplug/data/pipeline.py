"""What every data set shares after decoding a frame, and the base of the file-reading data modules.

Per item, in this order (:class:`FramePipeline`), for the frame and each of its adjacent frames:

1. pseudo labels are attached from files (:mod:`occplug.data.pseudo_labels`), then the plugins'
   label sources (:mod:`occplug.data.extensions`), at the original image resolution;
2. the images are resized to ``image_size`` (every split; recorded in ``img_aug``);
3. training only: the augmentation (:mod:`occplug.data.augment`); adjacent frames share the
   sample's image geometry per camera and its BEV transform;
4. the plugins' frame transforms of the split (:mod:`occplug.data.extensions`), on the whole sample.

:class:`ReaderDataset` adds lazy per-item decoding (subclasses implement :meth:`ReaderDataset.load`),
adjacent frames through a :class:`~occplug.data.sequences.SceneIndex`, the
``is_sequence_start`` flag, and an optional on-disk cache of decoded frames (before resizing, so
cached and uncached items are identical). :class:`ReaderDataModule` holds the arguments every
reader takes (batching, workers, pinned memory, image size, adjacent offsets, sequential sampling,
augmentation, pseudo labels, label sources, transforms, field rules, cache) and hands out the
sequential sampler.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol

import torch
from torch.utils.data import Dataset, Sampler

from occplug.context import ComponentBuilder
from occplug.geometry import GridSpec

from .augment import Augmentation, ImageTransform, apply_image_transforms
from .datamodule import OccDataModule
from .extensions import DataExtensions
from .frame import Frame
from .label_fraction import LabelCut, strip_voxel_labels
from .pseudo_labels import PseudoLabelSource
from .records import read_frame, save_frame
from .sequences import SceneIndex, stream_sampler

__all__ = [
    "LIDAR_FIELDS",
    "FramePipeline",
    "PipelineDataset",
    "PseudoLabeler",
    "ReaderDataModule",
    "ReaderDataset",
    "default_cache_root",
    "latest_mtime",
    "resolve_load_points",
    "stat_files",
]

#: The optional frame fields decoded from LiDAR files (``LIDAR_TOP`` sweeps, lidarseg, ``velodyne/``, ``labels/``).
LIDAR_FIELDS = frozenset({"points", "point_labels"})


def resolve_load_points(load_points: bool | None, required_fields: frozenset[str] | None) -> bool:
    """Whether a file reader opens LiDAR files.

    Args:
        load_points: the reader's ``load_points`` setting: True / False, or None = auto (load them
            iff the model reads :data:`LIDAR_FIELDS`; when the model never declared its fields,
            :meth:`~occplug.data.datamodule.OccDataModule.require_fields`, load them).
        required_fields: the declared fields, or None.

    Raises:
        ValueError: ``load_points`` is False but the model reads LiDAR fields.
    """
    needed = sorted(LIDAR_FIELDS & required_fields) if required_fields is not None else []
    if load_points is False and needed:
        raise ValueError(f"data.load_points is false but the model reads LiDAR points ({', '.join(needed)}); "
                         "set data.load_points to null (auto) or true")
    if load_points is None:
        return required_fields is None or bool(needed)
    return bool(load_points)


class PseudoLabeler(Protocol):
    """Anything that fills a frame's pseudo-label fields (file sources, the synthetic world's generator)."""

    def attach(self, frame: Frame) -> Frame: ...


def default_cache_root() -> Path:
    """``$OCCPLUG_CACHE`` or ``~/.cache/occplug``."""
    root = os.environ.get("OCCPLUG_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "occplug"


class FramePipeline:
    """Pseudo labels and label sources -> resize -> augmentation -> transforms (see the module docstring).

    Args:
        image_size: ``(H, W)`` every image is resized to, or None to keep it.
        pseudo: pseudo-label source, or None.
        augment: training augmentation, or None.
        label_sources: further labelers (``attach(frame) -> frame``), run after ``pseudo`` in order.
        transforms: callables ``frame -> frame`` run last, in order.
        strip_fill: with a label fraction, the ignore label that first overwrites the voxel labels of
            every frame marked ``has_voxel_labels = False`` (before any label source), else None.
    """

    def __init__(self, image_size: Sequence[int] | None = None, pseudo: PseudoLabeler | None = None,
                 augment: Augmentation | None = None, label_sources: Sequence[PseudoLabeler] = (),
                 transforms: Sequence[Callable[[Frame], Frame]] = (), strip_fill: int | None = None) -> None:
        self.strip_fill = strip_fill
        self.image_size = None if image_size is None else (int(image_size[0]), int(image_size[1]))
        self.pseudo = pseudo
        self.augment = augment if augment is not None and augment.active else None
        self.label_sources = tuple(label_sources)
        self.transforms = tuple(transforms)

    @property
    def active(self) -> bool:
        """Whether the pipeline changes frames at all."""
        return (self.image_size is not None or self.pseudo is not None or self.augment is not None
                or bool(self.label_sources) or bool(self.transforms) or self.strip_fill is not None)

    def prepare(self, frame: Frame) -> Frame:
        """Steps 1-2 on one frame (not its adjacent frames)."""
        if self.strip_fill is not None and not frame.has_voxel_labels:
            frame = strip_voxel_labels(frame, self.strip_fill)
        if self.pseudo is not None:
            frame = self.pseudo.attach(frame)
        for source in self.label_sources:
            frame = source.attach(frame)
        if self.image_size is not None and frame.image_size != self.image_size:
            t = ImageTransform.resize(frame.image_size, self.image_size)
            frame = apply_image_transforms(frame, [t] * frame.num_cameras)
        return frame

    def __call__(self, frame: Frame) -> Frame:
        adjacent = {k: self.prepare(v) for k, v in frame.adjacent.items()}
        frame = self.prepare(frame)
        frame.adjacent = adjacent
        if self.augment is not None:
            frame = self.augment(frame)
        for transform in self.transforms:
            frame = transform(frame)
        return frame


class ReaderDataset(Dataset[Frame]):
    """Base of the file readers: lazy decoding, adjacent frames, pipeline, cache.

    Subclasses set :attr:`scenes` (items in scene-major temporal order) and implement
    :meth:`load`. Item ``i``'s frame gets ``extras["is_sequence_start"]`` (first frame of its scene
    in this data set) and, for every offset ``k``, ``adjacent[k]`` = the frame ``k`` steps away in its
    scene, clamped at the scene's ends.

    Args:
        scenes: the scene structure of the items.
        offsets: adjacent-frame offsets.
        pipeline: applied to every item.
        cache_dir: folder for decoded frames (``<cache_dir>/<cache_key>/<token>.pt``), or None.
        cache_key: identifies what :meth:`load` returns (data set, index, options).
    """

    def __init__(self, scenes: SceneIndex, offsets: Sequence[int] = (), pipeline: FramePipeline | None = None,
                 cache_dir: str | Path | None = None, cache_key: dict[str, Any] | None = None) -> None:
        self.scenes = scenes
        self.offsets = tuple(int(k) for k in offsets)
        self.pipeline = pipeline
        self.unlabelled: frozenset[int] = frozenset()  # set by data.label_fraction (OccDataModule.dataset)
        self.cache_root: Path | None = None
        if cache_dir is not None:
            digest = hashlib.sha256(json.dumps(cache_key or {}, sort_keys=True, default=str).encode()).hexdigest()[:16]
            self.cache_root = Path(cache_dir) / digest

    def __len__(self) -> int:
        return self.scenes.num_items

    def load(self, index: int) -> Frame:
        """Decode item ``index`` from its files (no adjacent frames, no pipeline)."""
        raise NotImplementedError

    def token(self, index: int) -> str:
        """The sample token of item ``index`` (names its cache file)."""
        raise NotImplementedError

    def frame(self, index: int) -> Frame:
        """Item ``index`` decoded (through the cache when there is one), with ``is_sequence_start``."""
        frame = None
        path = None if self.cache_root is None else self.cache_root / f"{self.token(index)}.pt"
        if path is not None and path.is_file():
            try:
                frame = read_frame(path)
            except Exception:  # noqa: BLE001 (an unreadable cache entry is decoded again)
                frame = None
        if frame is None:
            frame = self.load(index)
            if path is not None:
                save_frame(frame, path)
        frame.extras["is_sequence_start"] = self.scenes.is_start(index)
        return frame

    def __getitem__(self, index: int) -> Frame:
        if not 0 <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} frames")
        frame = self.frame(index)
        for k in self.offsets:
            frame.adjacent[k] = self.frame(self.scenes.neighbour(index, k))
        mark_labelled(frame, index, self.scenes, self.unlabelled)
        return self.pipeline(frame) if self.pipeline is not None and self.pipeline.active else frame


def mark_labelled(frame: Frame, index: int, scenes: SceneIndex, unlabelled: frozenset[int]) -> None:
    """Set ``has_voxel_labels`` of item ``index`` and of its adjacent frames from the hidden items."""
    if not unlabelled:
        return
    frame.has_voxel_labels = index not in unlabelled
    for k, adjacent in frame.adjacent.items():
        adjacent.has_voxel_labels = scenes.neighbour(index, k) not in unlabelled


class PipelineDataset(Dataset[Frame]):
    """A dataset that already yields complete frames (e.g. the synthetic world), run through a pipeline.

    Args:
        base: the dataset.
        scenes: its scene structure (for the sequential sampler).
        pipeline: applied to every item.
    """

    def __init__(self, base: Dataset[Frame], scenes: SceneIndex, pipeline: FramePipeline) -> None:
        self.base = base
        self.scenes = scenes
        self.pipeline = pipeline
        self.unlabelled: frozenset[int] = frozenset()  # set by data.label_fraction (OccDataModule.dataset)

    def __len__(self) -> int:
        return len(self.base)  # type: ignore[arg-type]

    def __getitem__(self, index: int) -> Frame:
        frame = self.base[index]
        mark_labelled(frame, index, self.scenes, self.unlabelled)
        return self.pipeline(frame)


def check_image_size(image_size: Sequence[int] | None) -> tuple[int, int] | None:
    """Validate an ``image_size`` argument."""
    if image_size is None:
        return None
    if len(image_size) != 2 or min(int(v) for v in image_size) < 1:
        raise ValueError(f"image_size must be [H, W] with positive sizes, got {list(image_size)}")
    return int(image_size[0]), int(image_size[1])


def check_offsets(offsets: Sequence[int] | None) -> tuple[int, ...]:
    """Validate ``adjacent_offsets`` (non-zero integers, no repeats)."""
    out = tuple(int(k) for k in offsets or ())
    if any(k == 0 for k in out) or len(set(out)) != len(out):
        raise ValueError(f"adjacent_offsets must be distinct non-zero frame offsets, got {list(offsets or ())}")
    return out


class ReaderDataModule(OccDataModule):
    """Shared arguments and loaders of occplug's data modules (see the module docstring).

    Args:
        grid: the label grid.
        class_names, free_label, ignore_label: the taxonomy.
        batch_size: samples per batch on each device (= lanes of the sequential sampler).
        num_workers: loader worker processes.
        pin_memory: copy batches into pinned memory (faster host-to-GPU transfer).
        image_size: ``[H, W]`` every image is resized to (all splits), or None.
        adjacent_offsets: frame offsets loaded into ``Frame.adjacent`` (e.g. ``[-1, 1]``).
        sequential: stream the data in temporal order (:mod:`occplug.data.sequences`): true, or
            ``{run_length: N}`` to train on runs of ``N`` consecutive frames (default whole scenes);
            training slots each play their own runs, evaluation covers every frame once.
        augment: training augmentation (a photometric preset name or a mapping; see :mod:`occplug.data.augment`).
        pseudo_labels: file-based pseudo labels (see :mod:`occplug.data.pseudo_labels`), or None.
        cache_dir: cache decoded frames on disk under this folder, or None.
        label_sources: plugins' label sources, name -> ``{type: <label_source>, ...}``
            (:mod:`occplug.data.extensions`).
        transforms: plugins' frame transforms, a list of ``{type: <transform>, splits: [...], ...}``.
        fields: collate rules of extra per-sample fields, name -> ``stack`` | ``list`` | ``pad``
            (or ``{collate, pad_value}``); the label sources' and transforms' own rules are added.
        label_fraction: the share of training frames that keep their voxel labels, in (0, 1]
            (:mod:`occplug.data.label_fraction`).
        subset: ``all``, ``labelled`` or ``unlabelled``: the training frames used.
        label_unit: ``frame`` (interval sampling of frames) or ``scene`` (of whole scenes).
        registry: the registry ``label_sources`` and ``transforms`` are built from (the builder hands in its own).
    """

    def __init__(self, *, grid: GridSpec | dict, class_names: Sequence[str], free_label: int, ignore_label: int | None,
                 batch_size: int = 1, num_workers: int = 0, pin_memory: bool = False,
                 image_size: Sequence[int] | None = None, adjacent_offsets: Sequence[int] | None = None,
                 sequential: bool | dict = False, augment: str | dict | None = None, pseudo_labels: dict | None = None,
                 cache_dir: str | None = None, pseudo: PseudoLabeler | None = None,
                 label_sources: dict | None = None, transforms: list | None = None, fields: dict | None = None,
                 label_fraction: float = 1.0, subset: str = "all", label_unit: str = "frame",
                 registry: ComponentBuilder | None = None) -> None:
        super().__init__(grid=grid, batch_size=batch_size, num_workers=num_workers, class_names=class_names,
                         free_label=free_label, ignore_label=ignore_label)
        self.label_cut = LabelCut(label_fraction, subset, label_unit)
        if batch_size < 1 or num_workers < 0:
            raise ValueError(f"batch_size must be >= 1 and num_workers >= 0, got {batch_size} and {num_workers}")
        self.pin_memory = bool(pin_memory)
        self.image_size = check_image_size(image_size)
        self.adjacent_offsets = check_offsets(adjacent_offsets)
        self.sequential, self.stream_run_length = sequential_settings(sequential)
        if self.sequential and self.label_cut.subset != "all":
            raise ValueError(f"data.subset: '{self.label_cut.subset}' breaks scenes apart; it needs data.sequential: false")
        fill = fill_label(ignore_label, free_label)
        self.augmentation = Augmentation(augment, self.grid, fill_label=fill)
        self.pseudo: PseudoLabeler | None = pseudo or PseudoLabelSource.from_config(pseudo_labels, self.class_names)
        self.cache_dir = cache_dir
        self.extensions = DataExtensions(label_sources, transforms, fields, registry=registry, class_names=self.class_names,
                                         grid=self.grid, free_label=free_label, ignore_label=ignore_label)
        self.field_rules = dict(self.extensions.fields)

    def pipeline(self, split: str) -> FramePipeline:
        """The pipeline of ``split`` (augmentation in ``train`` only; the transforms of ``split``)."""
        strip = fill_label(self.ignore_label, self.free_label) if split == "train" and self.label_cut.active else None
        return FramePipeline(self.image_size, self.pseudo, self.augmentation if split == "train" else None,
                             tuple(self.extensions.label_sources.values()), self.extensions.transforms_for(split),
                             strip_fill=strip)

    def sampler(self, split: str, dataset: Dataset[Frame]) -> Sampler | None:
        """The sequential sampler when ``sequential`` is on (scene order shuffled per epoch in ``train``)."""
        if not self.sequential:
            return None
        scenes = getattr(dataset, "scenes", None)
        if not isinstance(scenes, SceneIndex):
            raise TypeError(f"{type(dataset).__name__} has no SceneIndex 'scenes'; it cannot be read sequentially")
        trainer = getattr(self, "trainer", None)
        replicas = rank = None
        if trainer is not None:
            replicas, rank = trainer.world_size, trainer.global_rank
        seed = int(torch.initial_seed()) % (1 << 31) if split == "train" else 0
        return stream_sampler(split, scenes, self.batch_size, run_length=self.stream_run_length, num_replicas=replicas,
                              rank=rank, seed=seed)


def fill_label(ignore_label: int | None, free_label: int) -> int:
    """The label written where nothing is known: the ignore label, else ``free``."""
    return ignore_label if ignore_label is not None else free_label


def sequential_settings(value: bool | dict | None) -> tuple[bool, int | None]:
    """``data.sequential`` (true/false or ``{run_length: N}``) -> ``(sequential, run_length)``."""
    if value is None or isinstance(value, bool):
        return bool(value), None
    if not isinstance(value, dict):
        raise ValueError(f"data.sequential: expected true, false or {{run_length: N}}, got {value!r}")
    extra = sorted(set(value) - {"run_length"})
    if extra:
        raise ValueError(f"data.sequential.{extra[0]}: unknown key (valid: run_length)")
    length = value.get("run_length")
    if length is not None and (not isinstance(length, int) or isinstance(length, bool) or length < 1):
        raise ValueError(f"data.sequential.run_length: expected a positive integer or null, got {length!r}")
    return True, length


def stat_files(paths: Sequence[tuple[Path, Callable[[int], str | None]] | Path]) -> None:
    """Check that files exist (and, given a size check, have a valid size); raise one line naming the first bad one.

    Args:
        paths: paths, or ``(path, check)`` pairs where ``check(size_in_bytes)`` returns an error text or None.
    """
    from .formats import FormatError

    for item in paths:
        path, check = (item, None) if isinstance(item, Path) else item
        try:
            size = path.stat().st_size
        except FileNotFoundError:
            raise FormatError(f"{path}: no such file") from None
        if check is not None:
            problem = check(size)
            if problem:
                raise FormatError(f"{path}: {problem}")


def latest_mtime(paths: Sequence[tuple[Path, Callable[[int], str | None]] | Path]) -> int:
    """The newest modification time (ns) among ``paths`` (as :func:`stat_files` takes them); missing files are skipped.

    Part of a decoded-frame cache key, so that frames of a rewritten tree are decoded again.
    """
    newest = 0
    for item in paths:
        path = item if isinstance(item, Path) else item[0]
        try:
            newest = max(newest, path.stat().st_mtime_ns)
        except FileNotFoundError:
            continue
    return newest
