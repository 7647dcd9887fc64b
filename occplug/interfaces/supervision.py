"""Kind ``supervision``: turn a batch and the model's outputs into losses."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from occplug.data.frame import Batch
from occplug.geometry import GridSpec

from .checks import CHECK_CHANNELS, assert_gradient
from .query import QueryResult
from .scene import Scene
from .view_transform import Lifted

__all__ = ["ModelOutputs", "SupervisionSource"]


@dataclass
class ModelOutputs:
    """Everything a forward pass produced, for supervision sources to read.

    The model fills it in forward order; a component that reads outputs (``reads_outputs`` or a
    head's ``reads``) receives it partly filled: what comes before it in the flow, plus the heads it
    reads.

    Attributes:
        image_features: ``(B, N, C, h, w)`` the image encoder's primary level (what the view
            transform read).
        lifted: the view transform's output (volume, optional depth distributions).
        scene: the scene representation.
        heads: each head's named outputs, keyed by the head's config name.
        query: ``query(head_name, points, times=None) -> QueryResult`` asks the queryable head
            ``model.heads.<head_name>`` about ``(B, P, 3)`` ego-frame points of the current frame at
            ``(B, P)`` times in seconds relative to it (``None``: all 0); see
            :meth:`~occplug.interfaces.OccupancyHead.query`. 4D query supervision uses this.
        image_levels: every level of the image encoder, finest first (``[image_features]`` for
            a single-scale encoder).
        encoded: each point encoder's ``(B, C, X, Y, Z)`` volume, keyed by its config name.
        extras: intermediate outputs components publish for supervision sources (a head's
            queries, masks); keys are ``<component>/<name>`` by convention.
        history: each past frame the model also encodes (``model.input_history``), keyed by its frame offset:
            that frame's ``image_levels``, ``image_features``, ``encoded`` and ``lifted``, its cameras and LiDAR
            moved into the **current** ego frame (so its grids lie on the current frame's grid).
    """

    image_features: Tensor | None
    lifted: Lifted | None
    scene: Scene | None
    heads: dict[str, dict[str, Tensor]]
    query: Callable[..., QueryResult]
    image_levels: list[Tensor] = field(default_factory=list)
    encoded: dict[str, Tensor] = field(default_factory=dict)
    extras: dict[str, object] = field(default_factory=dict)
    history: dict[int, ModelOutputs] = field(default_factory=dict)


class SupervisionSource(nn.Module, ABC):
    """A loss term family. ``weight`` scales every loss it returns.

    Contract:
        given: ``free_label`` and ``ignore_label`` (the data set's), the run's ``grid`` and ``num_classes``, and, to a
        source that takes it (one that owns layers reading the scene's features), ``in_channels`` (the scene's
        ``out_channels``); a source that declares ``scene_downsample`` in its ``given`` also gets the scene's
        ``downsample`` (1 where it has none).
        declares: ``weight``, ``training_mask``, ``requires`` (Frame fields it reads).
        conformance: trained on a small LSS model's outputs for a tiny-world batch.

    .. versionadded:: 0.1
    """

    #: Constructor arguments the model fills in when the config leaves them out.
    given: ClassVar[tuple[str, ...]] = ("free_label", "ignore_label", "grid", "num_classes", "in_channels")

    @classmethod
    def check_conformance(cls, component: SupervisionSource, batch: Batch, grid: GridSpec, model: nn.Module) -> None:
        """The kind's contract, checked: a non-empty dict of finite scalar losses whose gradients reach the
        model (``model``: a small LSS model on ``grid`` whose outputs train the source, unless the source
        supplies its own :meth:`conformance_outputs`).

        :func:`occplug.testing.check_component` runs it on every registered component of this kind.
        """
        source = component
        own = type(source).conformance_outputs(batch, grid, CHECK_CHANNELS)
        outputs = model(batch) if own is None else own
        losses = source(batch, outputs)
        assert isinstance(losses, dict) and losses, "a supervision source returns a non-empty dict of losses"
        for key, value in losses.items():
            assert value.dim() == 0 and torch.isfinite(value), f"loss '{key}' must be a finite scalar"
        total = torch.stack(list(losses.values())).sum()
        assert total.requires_grad, "the losses carry no gradient"
        total.backward()
        if own is None:
            assert_gradient(model, "model under this supervision")

    @classmethod
    def conformance_outputs(cls, batch: Batch, grid: Any, channels: int) -> ModelOutputs | None:
        """The :class:`ModelOutputs` the conformance check trains this source on, or None (the default) for a
        small LSS model's outputs on ``batch``. A source that reads heads or ``extras`` that model lacks returns
        its own (with tensors that require grad)."""
        return None

    #: Optional :class:`~occplug.data.Frame` fields this component reads (e.g. ``{"points"}``):
    #: data modules skip loading what no component requires (a camera-only model opens no LiDAR file).
    requires: frozenset[str] = frozenset()

    weight: float

    #: Config name of the head this source asks through :attr:`ModelOutputs.query` (``None``: none).
    #: A source that queries takes it as the constructor argument ``query_head`` and stores it here, so
    #: the model build (and config validation, from the argument) can check the head is queryable.
    query_head: str | None = None
    #: Whether its queries ask about other time steps (``times != 0``): the queried head must be temporal.
    #: Config validation reads the class attribute; a source whose need depends on its arguments sets it
    #: on the instance in its constructor (then the model build catches an impossible mix).
    needs_temporal_queries: bool = False

    @property
    def training_mask(self) -> str:
        """Which visibility mask restricts this source's targets: ``none``, ``camera``, ``lidar`` or
        ``camera_and_lidar`` (recorded in checkpoints and ``metrics.json`` beside the evaluation mask)."""
        return "none"

    @abstractmethod
    def forward(self, batch: Batch, outputs: ModelOutputs) -> dict[str, Tensor]:
        """Named, unweighted scalar losses (the model multiplies by ``weight`` and sums)."""
