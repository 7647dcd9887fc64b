"""Kind ``model``: what the runner (fit, validate, test, predict, checkpoints) reads of a model.

The core's :class:`~occplug.model.OccModel` implements it; a plugin may register its own model
class (kind ``model``) and the runner treats it the same, because it reads a model only through
this interface. Imported lazily (it pulls in Lightning).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

import lightning as L
from torch import Tensor

from occplug.data.frame import Batch
from occplug.geometry import GridSpec

__all__ = ["OccupancyModel"]


class OccupancyModel(L.LightningModule, ABC):
    """A LightningModule the runner can train, evaluate, predict with and checkpoint.

    Contract:
        given: ``grid`` (the evaluation grid, a mapping), ``class_names``, ``free_label``,
        ``ignore_label`` (from the data module), ``optimizer``, ``scheduler`` and ``metrics`` (the
        config's sections) and ``eval_mask`` (the run's evaluation mask; the core model gives its metrics
        the grid and, as ``mask``, the evaluation mask). A subclass may widen ``given``; config validation
        accepts a config that leaves any of them out.
        declares: the attributes and methods below. Its ``__init__`` arguments are the config's
        ``model`` node; nested components are declared with ``Annotated[dict, Slot(kind)]`` so
        config validation checks them.

    Attributes:
        grid: the evaluation grid :meth:`predict_occupancy` answers on.
        last_results: ``{"val"|"test": {metric key: value}}`` of the last evaluation epoch.
        last_tables: ``{metric name: per-class text table}`` of the last evaluation epoch.
        effective_batch: samples per optimizer step (an ``occplug.run.training.EffectiveBatch``), or None.
        effective_lr: the learning rate actually used, or None.
        run_config: the resolved run config (set by the runner; stored in checkpoints).

    .. versionadded:: 0.2
    """

    #: Constructor arguments the runner fills in when the config's ``model`` node leaves them out.
    given: ClassVar[tuple[str, ...]] = (
        "grid", "class_names", "free_label", "ignore_label", "optimizer", "scheduler", "metrics", "eval_mask",
    )

    grid: GridSpec
    last_results: dict[str, dict[str, float]]
    last_tables: dict[str, str]
    effective_batch: Any = None
    effective_lr: float | None = None
    run_config: dict[str, Any] | None = None

    @abstractmethod
    def predict_occupancy(self, batch: Batch) -> Tensor:
        """``(B, X, Y, Z)`` int64 class ids on :attr:`grid`; every metric and ``predict`` use this."""

    def head_logits(self, batch: Batch, head: str) -> Tensor:
        """``(B, K, X, Y, Z)`` logits of the named head on :attr:`grid`, in eval mode without gradients.

        Teacher pseudo labels (``phases.<name>.pseudo_labels_from``) read this; a model that cannot
        answer leaves the default, which says so in one line.
        """
        raise ValueError(f"{type(self).__name__} does not give the logits of head '{head}' (no head_logits)")

    def predict_step(self, batch: Batch, batch_idx: int) -> dict[str, Any]:
        """``{"token": [B sample tokens], "pred": (B, X, Y, Z) class ids}``: what ``occplug predict`` writes."""
        return {"token": list(batch.token), "pred": self.predict_occupancy(batch)}

    def required_fields(self) -> frozenset[str]:
        """Optional Frame fields some submodule reads (the union of their ``requires``), so the
        data module loads exactly those (a camera-only model opens no LiDAR file)."""
        out: set[str] = set()
        for module in self.modules():
            out |= set(getattr(module, "requires", ()))
        return frozenset(out)

    def training_masks(self) -> dict[str, str]:
        """``{supervision name: training mask}`` recorded beside the evaluation mask (empty: none)."""
        return {}

    def loss_weights(self) -> dict[str, float]:
        """``{supervision name: weight}`` of what trains this model (empty: nothing does).

        ``occplug fit`` refuses a model whose weights are empty or all <= 0 (it would train
        nothing); ``validate`` and ``predict`` accept it.
        """
        return {}

    def dry_run(self, batch: Batch) -> None:
        """One forward pass (and loss computation) on ``batch``, raising what the first training
        step would raise. The runner calls it on a deep copy of the model before anything is
        written, under ``torch.no_grad`` with the random-number state restored afterwards; the
        default runs :meth:`forward` and :meth:`predict_occupancy`."""
        self(batch)
        self.predict_occupancy(batch)

    def configure_callbacks(self) -> list[L.Callback]:
        """:class:`~occplug.streams.StreamStages` when a component holds a stream state (one store per loop:
        the sanity check and mid-epoch validation never touch the training state). A subclass that adds
        callbacks of its own extends this list."""
        from occplug.streams import StreamStages, find_streams

        return [StreamStages()] if any(True for _ in find_streams(self)) else []
