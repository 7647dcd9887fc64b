"""The component kinds: the one list of them, each naming the interface class that holds its contract.

A kind's *contract* lives on its interface class (``occplug.interfaces``): what the parent passes
in (``given``: constructor arguments a config may leave out), what it declares (``requires``
Frame fields, capabilities such as ``queryable`` or ``stateful``) and how the conformance check
builds its inputs (``conformance_inputs``). The registry, the config validator, the model builder
and the conformance check all read it from here, so adding a kind is one line.

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
    """

    name: str
    summary: str
    where: str

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
        Kind("encoder", "image encoder: (B, N, 3, H, W) images -> per-view feature maps (one or several scales)",
             "occplug.interfaces.encoder:ImageEncoder"),
        Kind("point_encoder", "point-cloud encoder: a batch's LiDAR points -> a feature volume (a LiDAR branch)",
             "occplug.interfaces.encoder:PointEncoder"),
        Kind("view_transform", "lifts per-view features into an ego-frame volume",
             "occplug.interfaces.view_transform:ViewTransform"),
        Kind("depth_net", "depth network of a lift-splat view transform: features (+ calibration) -> depth, context",
             "occplug.interfaces.depth_net:DepthNet"),
        Kind("scene", "scene representation read by heads and queried by supervision",
             "occplug.interfaces.scene:SceneRepresentation"),
        Kind("head", "prediction head (occupancy heads answer predict_occupancy); may read other heads",
             "occplug.interfaces.head:Head"),
        Kind("supervision", "turns a batch and model outputs into losses",
             "occplug.interfaces.supervision:SupervisionSource"),
        Kind("model", "the LightningModule composing the components", "occplug.interfaces.model:OccupancyModel"),
        Kind("data", "a LightningDataModule yielding occplug Frames", "occplug.data.datamodule:OccDataModule"),
        Kind("transform", "a frame transform every data module runs after augmentation (config data.transforms)",
             "occplug.data.extensions:FrameTransform"),
        Kind("label_source", "attaches labels to decoded frames in every data module (config data.label_sources)",
             "occplug.data.extensions:LabelSource"),
        Kind("metric", "a torchmetrics Metric over predicted and true occupancy", "occplug.metrics.base:OccMetric"),
        Kind("callback", "a Lightning Callback added to the Trainer (config section 'callbacks')",
             "lightning.pytorch.callbacks:Callback"),
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
