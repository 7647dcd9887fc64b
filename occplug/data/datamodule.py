"""The base of every occplug data module (registered under kind ``data``)."""

from __future__ import annotations

from collections.abc import Collection, Sequence

import lightning as L
import torch.distributed as dist
from torch.utils.data import DataLoader, Dataset, DistributedSampler, Sampler

from occplug.geometry import GridSpec

from .frame import Batch, FieldRule, Frame, FrameCollator
from .sequences import SceneEvalSampler, StreamDataset, StreamRunSampler

__all__ = ["EvalShardSampler", "OccDataModule"]


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
    """

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
        self.grid = GridSpec.from_config(grid)
        self.batch_size = batch_size
        self.num_workers = num_workers
        self.class_names = tuple(class_names)
        self.free_label = free_label
        self.ignore_label = ignore_label
        self._datasets: dict[str, Dataset[Frame]] = {}
        self.required_fields: frozenset[str] | None = None
        # plugins' extra fields (occplug.data.extensions); undeclared extras are collated as lists
        self.field_rules: dict[str, FieldRule] = {}

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
        """The (cached) dataset of ``split``."""
        if split not in self._datasets:
            self._datasets[split] = self.build_dataset(split)
        return self._datasets[split]

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
        return DataLoader(
            dataset,
            batch_size=batch_size,
            shuffle=shuffle,
            sampler=sampler,
            num_workers=self.num_workers,
            collate_fn=FrameCollator(self.field_rules),
            persistent_workers=self.num_workers > 0,
            pin_memory=self.pin_memory,
        )

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
