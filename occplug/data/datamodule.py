"""The base of every occplug data module (registered under kind ``data``)."""

from __future__ import annotations

import itertools
import os
import random
from collections.abc import Collection, Iterator, Sequence
from typing import Any, ClassVar

import lightning as L
import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, Dataset, DistributedSampler, Sampler

from occplug.context import parse_grid
from occplug.geometry import GridSpec

from .frame import Batch, FieldRule, Frame, FrameCollator
from .label_fraction import LabelCut, SubsetDataset
from .sequences import SceneEvalSampler, StreamDataset, StreamRunSampler, _dist_defaults

__all__ = ["EvalShardSampler", "OccDataModule", "ResumableLoader"]


class OccDataModule(L.LightningDataModule):
    """A LightningDataModule whose datasets yield :class:`~occplug.data.Frame` objects.

    Subclasses implement :meth:`build_dataset` for ``"train"``, ``"val"``, ``"test"`` and
    ``"predict"``; batching, workers and collation live here once.

    Args:
        grid: the label grid (``{range, voxel_size}``); predictions and metrics use it too.
        batch_size: samples per batch on each device.
        num_workers: data-loader worker processes (0 = load in the main process).
        class_names: names of the label ids, index = id.
        free_label: id of empty space in ``voxel_labels`` (Occ3D 17, SemanticKITTI 0).
        ignore_label: id to ignore in losses and metrics, or None.

    Attributes:
        required_fields: the optional :class:`~occplug.data.Frame` fields the model reads, as declared
            through :meth:`require_fields` (None until then = unknown: every field is loaded).
        field_rules: collate rules of extra per-sample fields (``Frame.extras``), used by the loaders
            and :meth:`collate`.
        label_cut: the training split's label fraction and subset (:mod:`occplug.data.label_fraction`);
            a subclass that takes ``label_fraction`` / ``subset`` sets it.
    """

    #: Constructor arguments the runner fills in when the config leaves them out: the run's top-level ``grid``.
    given: ClassVar[tuple[str, ...]] = ("grid",)

    def __init__(
        self,
        grid: GridSpec | dict,
        batch_size: int = 1,
        num_workers: int = 0,
        class_names: Sequence[str] = (),
        free_label: int = 17,
        ignore_label: int | None = 255,
    ) -> None:
        super().__init__()
        self.grid = parse_grid(grid)  # a data module's own `grid` knob, as its config (or a caller) wrote it
        self.batch_size = batch_size
        self.num_workers = num_workers
        self.class_names = tuple(class_names)
        self.free_label = free_label
        self.ignore_label = ignore_label
        self._datasets: dict[str, Dataset[Frame]] = {}
        self.required_fields: frozenset[str] | None = None
        # plugins' extra fields (occplug.data.extensions); undeclared extras are collated as lists
        self.field_rules: dict[str, FieldRule] = {}
        self._train_loader: ResumableLoader | None = None
        self._train_resume: dict[str, Any] | None = None
        self.label_cut = LabelCut()

    def state_dict(self) -> dict[str, Any]:
        """The training loader's :meth:`~ResumableLoader.position` when a checkpoint is taken inside an
        epoch (Lightning stores this in every checkpoint), else nothing."""
        loader, trainer = self._train_loader, self.trainer
        if loader is None or trainer is None or not 0 < loader.batches_done < trainer.num_training_batches:
            return {}
        return {"train_loader": loader.position()}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Resume the training loader inside its epoch (Lightning calls this before it asks for loaders)."""
        self._train_resume = state_dict.get("train_loader")
        if self._train_resume is not None and self._train_loader is not None:
            self._train_loader.resume_at(self._train_resume)
            self._train_resume = None

    def require_fields(self, fields: Collection[str]) -> None:
        """Declare the optional frame fields the model's components, metrics and callbacks read.

        The runner calls this once, after building the model and before any training or evaluation
        (e.g. ``{"points", "point_labels"}`` for a LiDAR-supervised model, an empty set for a
        camera-only one). File readers then skip what nobody reads (a camera-only run opens no LiDAR
        file) and check the files that are needed. Datasets built earlier are dropped, so they are
        rebuilt with the declared fields.

        Raises:
            ValueError: a field the data module's settings exclude (one line naming the setting).
            FormatError: a file the declared fields need is missing or corrupt (one line naming it).
        """
        if isinstance(fields, str):
            raise TypeError(f"require_fields: expected a collection of field names, got the string {fields!r}")
        self.required_fields = frozenset(str(f) for f in fields)
        self._datasets.clear()

    def build_dataset(self, split: str) -> Dataset[Frame]:
        """Return the dataset of ``split`` (``train``, ``val``, ``test`` or ``predict``)."""
        raise NotImplementedError

    def dataset(self, split: str) -> Dataset[Frame]:
        """The (cached) dataset of ``split``; the training split cut by :attr:`label_cut`."""
        if split not in self._datasets:
            dataset = self.build_dataset(split)
            if split == "train" and self.label_cut.active:
                dataset = self._cut(dataset)
            self._datasets[split] = dataset
        return self._datasets[split]

    def _cut(self, dataset: Dataset[Frame]) -> Dataset[Frame]:
        if not hasattr(dataset, "unlabelled"):
            raise ValueError(
                f"data.label_fraction: {type(self).__name__}'s training set ({type(dataset).__name__}) cannot hide "
                "voxel labels (it has no 'unlabelled' attribute; see occplug.data.pipeline.PipelineDataset)"
            )
        n, scenes = len(dataset), getattr(dataset, "scenes", None)  # type: ignore[arg-type]
        dataset.unlabelled = self.label_cut.unlabelled(n, scenes)  # type: ignore[attr-defined]
        if self.label_cut.subset == "all":
            return dataset
        return SubsetDataset(dataset, self.label_cut.selected(n, scenes))

    #: Copy batches into pinned (page-locked) memory in the loader, for faster host-to-GPU copies.
    pin_memory: bool = False

    def collate(self, frames: list[Frame]) -> Batch:
        """Collate frames as this data module's loaders do (with :attr:`field_rules`)."""
        return FrameCollator(self.field_rules)(frames)

    def sampler(self, split: str, dataset: Dataset[Frame]) -> Sampler | None:
        """A sampler replacing the default one of ``split`` (e.g. a sequential sampler), or None.

        A returned sampler that is a ``DistributedSampler`` is left in place by Lightning under DDP.
        """
        return None

    def _loader(self, split: str, shuffle: bool) -> DataLoader[Batch]:
        dataset = self.dataset(split)
        sampler = self.sampler(split, dataset)
        batch_size: int | None = self.batch_size
        if sampler is not None:
            shuffle = False
            if isinstance(sampler, (StreamRunSampler, SceneEvalSampler)):
                dataset = StreamDataset(dataset)  # reads StreamItems / index lists
            if isinstance(sampler, SceneEvalSampler):
                batch_size = None  # it yields whole (shrinking) batches
        elif split in ("val", "test"):
            sampler = EvalShardSampler.for_current_process(dataset)
        elif shuffle:  # a permutation per (seed, epoch), not the global RNG: a resumed epoch replays it
            replicas, rank = _dist_defaults(None, None)
            seed = int(os.environ.get("PL_GLOBAL_SEED", 0))
            sampler, shuffle = DistributedSampler(dataset, replicas, rank, shuffle=True, seed=seed), False
        loader = (ResumableLoader if split == "train" else DataLoader)(
            dataset,
            batch_size=batch_size,
            shuffle=shuffle,
            sampler=sampler,
            num_workers=self.num_workers,
            collate_fn=FrameCollator(self.field_rules),
            persistent_workers=self.num_workers > 0,
            pin_memory=self.pin_memory,
        )
        if isinstance(loader, ResumableLoader):
            self._train_loader = loader
            if self._train_resume is not None:
                loader.resume_at(self._train_resume)
                self._train_resume = None
        return loader

    def train_dataloader(self) -> DataLoader[Batch]:
        return self._loader("train", shuffle=True)

    def val_dataloader(self) -> DataLoader[Batch]:
        return self._loader("val", shuffle=False)

    def test_dataloader(self) -> DataLoader[Batch]:
        return self._loader("test", shuffle=False)

    def predict_dataloader(self) -> DataLoader[Batch]:
        return self._loader("predict", shuffle=False)


class EvalShardSampler(DistributedSampler):
    """Rank ``r`` of ``W`` reads samples ``r, r + W, r + 2W, ...``: every sample exactly once.

    Lightning's default evaluation sampler (a ``DistributedSampler``) repeats samples to give every
    rank the same count, which would count them twice in the metrics; with this one the summed
    metric states over the ranks equal a single process's. Ranks may then run one batch more or
    less; occplug's evaluation steps run no collective operation per batch (metrics and logged
    values sync once, at the epoch end), so uneven counts are safe.
    """

    def __init__(self, dataset: Dataset, num_replicas: int, rank: int) -> None:
        super().__init__(dataset, num_replicas=num_replicas, rank=rank, shuffle=False, drop_last=False)
        self.num_samples = len(range(rank, len(dataset), num_replicas))  # type: ignore[arg-type]
        self.total_size = len(dataset)  # type: ignore[arg-type]

    def __iter__(self):  # type: ignore[override]
        return iter(range(self.rank, self.total_size, self.num_replicas))

    @classmethod
    def for_current_process(cls, dataset: Dataset) -> EvalShardSampler | None:
        """The sampler of this rank inside an initialised process group of 2+ ranks, else ``None``
        (also when there are fewer samples than ranks: then Lightning's padding sampler keeps every
        rank busy)."""
        if not (dist.is_available() and dist.is_initialized()):
            return None
        world = dist.get_world_size()
        if world < 2 or len(dataset) < world:  # type: ignore[arg-type]
            return None
        return cls(dataset, world, dist.get_rank())


class ResumableLoader(DataLoader):
    """A ``DataLoader`` that resumes mid-epoch where a checkpoint left it.

    :meth:`position` is what a checkpoint stores (:meth:`OccDataModule.state_dict` carries it);
    after :meth:`resume_at`, the next pass skips the batches already trained on *by index* (no sample is
    loaded) and, right before fetching its first batch, restores the random-number generators (torch
    CPU/CUDA, numpy, ``random``) to their state at the checkpoint. With a sampler whose order depends
    only on ``(seed, epoch)`` (every occplug training sampler) and ``num_workers: 0``, the resumed pass
    yields the very batches, and draws the very augmentations, the uninterrupted one would have.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.batches_done = 0  # batches handed out by the current pass
        self._skip = 0  # batches the index iterator made next skips
        self._resume: dict[str, Any] | None = None

    @property
    def _index_sampler(self) -> Any:  # torch builds every pass's index iterator from this
        return _SkipFirst(super()._index_sampler, self)

    def __iter__(self) -> Iterator[Any]:  # type: ignore[override]
        self.batches_done = 0
        return self._counted(super().__iter__())

    def _counted(self, inner: Iterator[Any]) -> Iterator[Any]:
        # Applied at the first next(), not in __iter__: Lightning makes the iterator before it restores
        # a checkpoint (to count the steps of an epoch), and the loader draws a worker seed when it does.
        if self._resume is not None:
            resume, self._resume = self._resume, None
            self._skip = int(resume["batches"])
            inner = super().__iter__()  # a new index iterator, without the trained batches
            self._skip = 0
            self.batches_done = int(resume["batches"])
            _set_rng_state(resume["rng"])
        for batch in inner:
            self.batches_done += 1
            yield batch

    def position(self) -> dict[str, Any]:
        """``{"batches": batches of this pass handed out, "rng": generator states}`` (plain types and
        tensors only, so checkpoints stay loadable with ``weights_only=True``)."""
        return {"batches": self.batches_done, "rng": _rng_state()}

    def resume_at(self, position: dict[str, Any]) -> None:
        """Make the next pass continue after ``position["batches"]`` batches (see the class doc)."""
        self._resume = dict(position)


class _SkipFirst:
    """An index sampler (or batch sampler) whose next iterator drops the loader's pending ``_skip`` items."""

    def __init__(self, base: Any, loader: ResumableLoader) -> None:
        self.base, self.loader = base, loader

    def __len__(self) -> int:
        return len(self.base)

    def __iter__(self) -> Iterator[Any]:
        return itertools.islice(iter(self.base), self.loader._skip, None)  # lazy: nothing drawn before next()


def _rng_state() -> dict[str, Any]:
    kind, keys, pos, has_gauss, gauss = np.random.get_state()
    state: dict[str, Any] = {
        "torch": torch.get_rng_state(),
        "numpy": [kind, keys.tolist(), pos, has_gauss, gauss],
        "python": random.getstate(),
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    kind, keys, pos, has_gauss, gauss = state["numpy"]
    np.random.set_state((kind, np.asarray(keys, dtype=np.uint32), pos, has_gauss, gauss))
    random.setstate(tuple(x if not isinstance(x, list) else tuple(x) for x in state["python"]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
