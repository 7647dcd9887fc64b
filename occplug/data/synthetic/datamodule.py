"""``SyntheticDataModule``: the synthetic world as an :class:`~occplug.data.OccDataModule`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, ClassVar

from torch.utils.data import Dataset, Sampler

from occplug.constraints import Fraction, Length, NonNegative, Positive, Range
from occplug.context import ComponentBuilder
from occplug.data.classes import OCC3D_CLASSES, OCC3D_FREE
from occplug.data.frame import Frame
from occplug.data.pipeline import PipelineDataset, ReaderDataModule
from occplug.data.sequences import SceneIndex

from .config import SyntheticWorldConfig
from .config import preset as get_preset
from .dataset import SyntheticDataset, default_cache_dir, pregenerate

__all__ = ["SyntheticDataModule"]


class SyntheticDataModule(ReaderDataModule):
    """The procedural driving world (no downloads), registered as data ``synthetic``.

    Every size knob defaults to ``None``, meaning the preset's value. The ``predict`` split reads
    the ``val`` scenes. Frames are generated on first use and cached on disk (see
    :class:`~occplug.data.synthetic.SyntheticDataset`); :meth:`prepare_data` generates the training and
    validation splits up front (in parallel processes, with a progress bar); ``setup("test")`` the test split.

    Args:
        preset: ``tiny`` (tests), ``default`` (a CPU run of minutes), ``aligned`` (the default world, ground on
            voxel centres), ``testbed`` (the calibrated test bed of issue 52), ``occ3d`` (Occ3D size) or
            ``long_range`` (scene, LiDAR and pseudo depth to 250 m).
        grid: ``{range, voxel_size}`` of the label grid, replacing the preset's.
        seed: world seed.
        train_scenes, val_scenes, test_scenes: scenes per split.
        frames_per_scene: frames of every scene (train and evaluation splits alike).
        eval_frames_per_scene: frames of every val/test scene, replacing ``frames_per_scene``'s value
            there (a stream needs long evaluation scenes: e.g. 16).
        image_size: ``[H, W]`` of every camera.
        num_cameras: 1..6 (front, front-right, front-left, back, back-left, back-right).
        lidar_beams: LiDAR rings.
        lidar_range_noise, lidar_dropout: LiDAR range error (metres, standard deviation) and the share of
            returns lost (see :class:`~occplug.data.synthetic.SyntheticWorldConfig`).
        fps: frame rate, Hz.
        image_noise: standard deviation of the cameras' per-pixel sensor noise (images in [0, 1]; default
            world 0.01): a harder world, where one frame's images say less.
        adjacent_offsets: frame offsets to load as ``Frame.adjacent`` (e.g. ``[-1, 1]``).
        cache: store generated frames on disk.
        cache_dir: cache root; default ``$OCCPLUG_CACHE/synthetic`` or ``~/.cache/occplug/synthetic``.
        batch_size: samples per batch on each device.
        num_workers: data-loader worker processes.
        pin_memory: pin batches in memory (for GPU training).
        sequential: read scenes in temporal order (:mod:`occplug.data.sequences`; or ``{run_length: N}``).
        augment: training augmentation (:mod:`occplug.data.augment`).
        pseudo_labels: ``{synthetic: <realism>}`` makes the world's own imperfect pseudo labels on the
            fly (:mod:`occplug.data.synthetic.pseudo`; realism = ``perfect``, ``default``, ``noisy`` or a
            knob mapping; optional ``kinds: [depth, semantics, features]``; ``depth_max`` defaults to at
            least the world's LiDAR range), or file sources as for any
            reader (:mod:`occplug.data.pseudo_labels`).
        registry: the registry ``label_sources`` and ``transforms`` are built from (the builder hands it in).
        label_sources, transforms, fields: plugins' label sources, frame transforms and field collate
            rules (:mod:`occplug.data.extensions`).
        label_fraction, subset: label-efficient training: the share of training frames that keep their
            voxel labels (interval sampling) and which side of that cut trains (``all``, ``labelled``,
            ``unlabelled``); see :mod:`occplug.data.label_fraction`.
        label_unit: ``frame`` (interval sampling of frames) or ``scene`` (whole scenes keep or lose labels).

    Attributes:
        world_config: the resolved :class:`~occplug.data.synthetic.SyntheticWorldConfig`.
    """

    #: the label names, index = id (config validation reads them before anything is built)
    class_names: ClassVar[tuple[str, ...]] = OCC3D_CLASSES

    def __init__(
        self,
        preset: str = "default",
        grid: dict | None = None,
        seed: int | None = None,
        train_scenes: Annotated[int | None, NonNegative] = None,
        val_scenes: Annotated[int | None, NonNegative] = None,
        test_scenes: Annotated[int | None, NonNegative] = None,
        frames_per_scene: Annotated[int | None, Positive] = None,
        eval_frames_per_scene: Annotated[int | None, Positive] = None,
        image_size: Annotated[list[Annotated[int, Range(low=4)]] | None, Length(exact=2)] = None,
        num_cameras: Annotated[int | None, Range(low=1, high=6)] = None,
        lidar_beams: Annotated[int | None, Positive] = None,
        lidar_range_noise: Annotated[float | None, NonNegative] = None,
        lidar_dropout: Annotated[float | None, NonNegative] = None,
        fps: Annotated[float | None, Positive] = None,
        image_noise: Annotated[float | None, NonNegative] = None,
        adjacent_offsets: list[int] | None = None,
        cache: bool = True,
        cache_dir: str | None = None,
        batch_size: Annotated[int, Positive] = 1,
        num_workers: Annotated[int, NonNegative] = 0,
        pin_memory: bool = False,
        sequential: bool | dict = False,
        augment: str | dict | None = None,
        pseudo_labels: dict | None = None,
        label_sources: dict | None = None,
        registry: ComponentBuilder | None = None,
        transforms: list | None = None,
        fields: dict | None = None,
        label_fraction: Annotated[float, Fraction] = 1.0,
        subset: str = "all",
        label_unit: str = "frame",
    ) -> None:
        knobs = {
            "grid": grid,
            "seed": seed,
            "train_scenes": train_scenes,
            "val_scenes": val_scenes,
            "test_scenes": test_scenes,
            "frames_per_scene": frames_per_scene,
            "eval_frames_per_scene": frames_per_scene if eval_frames_per_scene is None else eval_frames_per_scene,
            "image_size": image_size,
            "num_cameras": num_cameras,
            "lidar_beams": lidar_beams,
            "lidar_range_noise": lidar_range_noise,
            "lidar_dropout": lidar_dropout,
            "fps": fps,
            "image_noise": image_noise,
            "adjacent_offsets": adjacent_offsets,
        }
        config = get_preset(preset).replace(**{k: v for k, v in knobs.items() if v is not None})
        generated = None
        if pseudo_labels and "synthetic" in pseudo_labels:
            from .pseudo import SyntheticPseudoLabels

            extra = sorted(set(pseudo_labels) - {"synthetic", "kinds"})
            if extra:
                raise ValueError(f"data.pseudo_labels.{extra[0]}: with 'synthetic' only 'kinds' may be given")
            kinds = tuple(pseudo_labels.get("kinds") or ("depth", "semantics", "features"))
            root = (Path(cache_dir) if cache_dir else default_cache_dir()) if cache else None
            generated = SyntheticPseudoLabels(
                _realism(pseudo_labels["synthetic"], config),
                kinds=kinds,
                cache_dir=None if root is None else root / "pseudo" / config.cache_key(),
            )
            pseudo_labels = None
        super().__init__(
            grid=config.grid,
            batch_size=batch_size,
            num_workers=num_workers,
            class_names=self.class_names,
            free_label=OCC3D_FREE,
            ignore_label=255,
            pin_memory=pin_memory,
            sequential=sequential,
            augment=augment,
            pseudo_labels=pseudo_labels,
            pseudo=generated,
            label_sources=label_sources,
            registry=registry,
            transforms=transforms,
            fields=fields,
            label_fraction=label_fraction,
            subset=subset,
            label_unit=label_unit,
        )
        self.preset = preset
        self.world_config: SyntheticWorldConfig = config
        self.cache_dir: Path | None = (Path(cache_dir) if cache_dir else default_cache_dir()) if cache else None

    def build_dataset(self, split: str) -> Dataset[Frame]:
        """The :class:`~occplug.data.synthetic.SyntheticDataset` of ``split`` (``predict`` = ``val``), run
        through a :class:`~occplug.data.pipeline.PipelineDataset` when pseudo labels or augmentation are on."""
        dataset = SyntheticDataset(self.world_config, split, cache_dir=self.cache_dir)
        pipeline = self.pipeline(split)
        return PipelineDataset(dataset, _scenes(dataset), pipeline) if pipeline.active else dataset

    def sampler(self, split: str, dataset: Dataset[Frame]) -> Sampler | None:
        """The sequential sampler when ``sequential`` is on."""
        if self.sequential and isinstance(dataset, SyntheticDataset):
            dataset = PipelineDataset(dataset, _scenes(dataset), self.pipeline(split))
        return super().sampler(split, dataset)

    def prepare_data(self) -> None:
        """Generate and cache the train and val frames not cached yet (no-op without cache).

        The test split is left to ``setup("test")``: a ``fit`` never reads it.
        """
        if self.cache_dir is not None:
            pregenerate([self._world(split) for split in ("train", "val")], pseudo=self._cached_pseudo())

    def setup(self, stage: str) -> None:
        """Before ``test``, generate the test split the way :meth:`prepare_data` does the others."""
        if stage == "test":
            self.pregenerate("test")

    def pregenerate(self, split: str) -> None:
        """Generate and cache every frame of ``split`` not cached yet (no-op without cache)."""
        if self.cache_dir is None:
            return
        self._world(split).pregenerate(progress=True, pseudo=self._cached_pseudo())

    def _world(self, split: str) -> SyntheticDataset:
        dataset = self.dataset(split)
        while not isinstance(dataset, SyntheticDataset):  # through the pipeline and a data.subset
            dataset = dataset.base  # type: ignore[attr-defined]
        return dataset

    def _cached_pseudo(self) -> object | None:
        """The synthetic pseudo labeler when it caches its maps (then they are made with the world), else None."""
        labeler = self.pseudo
        return labeler if getattr(labeler, "cache_dir", None) is not None and hasattr(labeler, "is_cached") else None


def _realism(spec: object, config: SyntheticWorldConfig) -> object:
    """The pseudo-label realism, its ``depth_max`` raised to the LiDAR range unless the spec sets it
    (so the ``long_range`` world's pseudo depth reaches as far as its LiDAR)."""
    from dataclasses import replace

    from .pseudo import pseudo_realism

    realism = pseudo_realism(spec)  # type: ignore[arg-type]
    if isinstance(spec, dict) and "depth_max" in spec:
        return realism
    return replace(realism, depth_max=max(realism.depth_max, config.lidar_max_range))


def _scenes(dataset: SyntheticDataset) -> SceneIndex:
    names = [f"synth-{dataset.split}-{i:04d}" for i in range(dataset.num_scenes)]
    return SceneIndex.regular(names, dataset.frames_per_scene)
