"""The component kinds: the one list of them, each naming the interface class that holds its contract.

A kind's *contract* lives on its interface class (``occplug.interfaces`` and the data, metric modules): what the
parent passes in (``given``: constructor arguments a config may leave out), what it declares (``requires`` Frame
fields, capabilities such as ``queryable`` or ``stateful``), how the conformance check builds its inputs
(``conformance_inputs``) and the check itself (``check_conformance``). Its :class:`Kind` entry here adds where
it sits in a run's config (``place``) and the contract in one line (``contract``); the registry, the config
validator, the model builder, the conformance check and the table of kinds in ``docs/plugins.md``
(:func:`occplug.docs.markdown_table`) all read it from here.

Adding a kind takes its interface class and one :class:`Kind` line; the registry, validation, ``occplug
plugins``, the conformance sweep and the docs table follow from them. Where the kind's components are *called*
is code: the core model (``occ_model``, :mod:`occplug.model`) calls the model kinds in its forward, the data
module the data kinds; a new kind that the core model should call also needs that call there (or a plugin
model that calls it).

Interface classes are imported lazily (:meth:`Kind.interface`), so ``occplug.registry`` stays light.
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

__all__ = ["KINDS", "Kind", "given_arguments"]


@dataclass(frozen=True)
class Kind:
    """One component kind.

    Attributes:
        name: the kind's name (a config's slots and ``registry.add`` use it).
        summary: what a component of this kind does, one line (``occplug plugins`` shows it).
        where: ``module:Class`` of the interface class every component of the kind subclasses.
        place: where a component of the kind sits in a run's config.
        contract: what it takes and returns, one line (markdown), for the docs' table of kinds.
    """

    name: str
    summary: str
    where: str
    place: str = ""
    contract: str = ""

    def interface(self) -> type:
        """The interface class (imported on first use)."""
        module, _, attr = self.where.partition(":")
        return getattr(importlib.import_module(module), attr)

    def given(self) -> tuple[str, ...]:
        """Arguments the parent passes to every component of this kind (the interface's ``given``)."""
        return tuple(getattr(self.interface(), "given", ()))


#: Every kind, in the order ``occplug plugins`` lists them.
KINDS: dict[str, Kind] = {
    k.name: k
    for k in (
        Kind(
            "encoder",
            "image encoder: (B, N, 3, H, W) images -> per-view feature maps (one or several scales)",
            "occplug.interfaces.encoder:ImageEncoder",
            "model.encoder",
            "`(B, N, 3, H, W)` images in [0, 1] → `(B, N, C, H/stride, W/stride)`, or a list of levels (finest "
            "first; `level_channels`, `level_strides`, `primary_level`)",
        ),
        Kind(
            "point_encoder",
            "point-cloud encoder: a batch's LiDAR points -> a feature volume (a LiDAR branch)",
            "occplug.interfaces.encoder:PointEncoder",
            "model.point_encoders.<name>",
            "`batch` (its `points`) → `(B, C, X, Y, Z)` on its `grid`; a model may hold several",
        ),
        Kind(
            "view_transform",
            "lifts per-view features into an ego-frame volume",
            "occplug.interfaces.view_transform:ViewTransform",
            "model.view_transform",
            "`(features, batch)` → `Lifted(volume (B, C, X, Y, Z), grid, depth_probs?, depth_bins?)`",
        ),
        Kind(
            "depth_net",
            "depth network of a lift-splat view transform: features (+ calibration) -> depth, context",
            "occplug.interfaces.depth_net:DepthNet",
            "model.view_transform.depth_net",
            "`(features, batch)` → `DepthAndContext(depth_logits, context)`",
        ),
        Kind(
            "scene",
            "scene representation read by heads and queried by supervision",
            "occplug.interfaces.scene:SceneRepresentation",
            "model.scene",
            "`(lifted, batch)` → `Scene` with `features`, `grid`, `sample(points (B, P, 3)) -> (B, P, C)`",
        ),
        Kind(
            "head",
            "prediction head (occupancy heads answer predict_occupancy); may read other heads",
            "occplug.interfaces.head:Head",
            "model.heads.<name>",
            "`(scene, batch)` → named tensors; occupancy heads answer `occupancy_logits(scene, grid)`, queryable "
            "ones `query(scene, points, times=None) -> QueryResult`",
        ),
        Kind(
            "supervision",
            "turns a batch and model outputs into losses",
            "occplug.interfaces.supervision:SupervisionSource",
            "model.supervision.<name>",
            "`(batch, outputs: ModelOutputs)` → named unweighted scalar losses; `weight` scales them",
        ),
        Kind(
            "model",
            "the LightningModule composing the components",
            "occplug.interfaces.model:OccupancyModel",
            "model",
            "`predict_occupancy(batch) -> (B, X, Y, Z)`; the runner reads a model only through this interface",
        ),
        Kind(
            "data",
            "a LightningDataModule yielding occplug Frames",
            "occplug.data.datamodule:OccDataModule",
            "data",
            "yields `Frame`s, collated into `Batch`",
        ),
        Kind(
            "transform",
            "a frame transform every data module runs after augmentation (config data.transforms)",
            "occplug.data.extensions:FrameTransform",
            "data.transforms[]",
            "`frame -> frame`, after augmentation, in the splits named by `splits:`",
        ),
        Kind(
            "label_source",
            "attaches labels to decoded frames in every data module (config data.label_sources)",
            "occplug.data.extensions:LabelSource",
            "data.label_sources.<name>",
            "attaches labels to decoded frames; declares `fields` with collate rules",
        ),
        Kind(
            "metric",
            "a torchmetrics Metric over predicted and true occupancy",
            "occplug.metrics.base:OccMetric",
            "metrics[]",
            "`update(pred (B, X, Y, Z), batch)`, `compute() -> dict`",
        ),
        Kind(
            "callback",
            "a Lightning Callback added to the Trainer (config section 'callbacks')",
            "lightning.pytorch.callbacks:Callback",
            "callbacks.<name>",
            "a Lightning `Callback` added to the Trainer",
        ),
    )
}


def given_arguments(kind: str, factory: Callable[..., Any] | None = None) -> set[str]:
    """Constructor arguments of ``factory`` (a component of ``kind``) that its parent fills in.

    A class may widen its kind's ``given`` with its own ``given`` attribute (a plugin model that
    injects more into its components, or a view transform that takes the encoder's scales).
    """
    out = set(KINDS[kind].given()) if kind in KINDS else set()
    if factory is not None and inspect.isclass(factory):
        out |= set(getattr(factory, "given", ()))
    return out
