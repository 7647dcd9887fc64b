"""The base of every occplug data module (registered under kind ``data``)."""

from __future__ import annotations

from collections.abc import Sequence

import lightning as L
from torch.utils.data import DataLoader, Dataset

from occplug.geometry import GridSpec

from .frame import Batch, Frame, collate_frames

__all__ = ["OccDataModule"]


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

    def build_dataset(self, split: str) -> Dataset[Frame]:
        """Return the dataset of ``split`` (``train``, ``val``, ``test`` or ``predict``)."""
        raise NotImplementedError

    def dataset(self, split: str) -> Dataset[Frame]:
        """The (cached) dataset of ``split``."""
        if split not in self._datasets:
            self._datasets[split] = self.build_dataset(split)
        return self._datasets[split]

    def _loader(self, split: str, shuffle: bool) -> DataLoader[Batch]:
        return DataLoader(
            self.dataset(split),
            batch_size=self.batch_size,
            shuffle=shuffle,
            num_workers=self.num_workers,
            collate_fn=collate_frames,
            persistent_workers=self.num_workers > 0,
        )

    def train_dataloader(self) -> DataLoader[Batch]:
        return self._loader("train", shuffle=True)

    def val_dataloader(self) -> DataLoader[Batch]:
        return self._loader("val", shuffle=False)

    def test_dataloader(self) -> DataLoader[Batch]:
        return self._loader("test", shuffle=False)

    def predict_dataloader(self) -> DataLoader[Batch]:
        return self._loader("predict", shuffle=False)
