"""The one toy plugin of the registry and config tests (not installed: registered as an object or an entry point)."""

from __future__ import annotations

from typing import Annotated, Literal

from torch import Tensor, nn

import occplug
from occplug.interfaces.model import OccupancyModel
from occplug.slots import Slot


class ToyEncoder(occplug.ImageEncoder):
    """A toy encoder with typed arguments."""

    def __init__(
        self, channels: int, scale: float = 1.0, mode: Literal["a", "b"] = "a", name: str | None = None
    ) -> None:
        super().__init__()
        self.out_channels, self.stride = channels, 1
        self.scale, self.mode = scale, mode
        self.conv = nn.Conv2d(3, channels, 1)

    def forward(self, images: Tensor) -> Tensor:
        b, n = images.shape[:2]
        return self.conv(images.flatten(0, 1)).unflatten(0, (b, n)) * self.scale


class OtherEncoder(occplug.ImageEncoder):
    """Another toy encoder sharing 'channels' but not 'scale'."""

    def __init__(self, channels: int, depth: int = 2) -> None:
        super().__init__()
        self.out_channels, self.stride, self.depth = channels, 1, depth

    def forward(self, images: Tensor) -> Tensor:
        return images


class ToyModel(OccupancyModel):
    """A toy 'model' with a nested encoder slot and a mapping of heads."""

    def __init__(
        self,
        encoder: Annotated[dict, Slot("encoder")],
        extras: Annotated[dict, Slot("encoder", mapping=True)] | None = None,
        lr: float = 0.1,
    ) -> None:
        super().__init__()

    def predict_occupancy(self, batch: object) -> Tensor:
        raise NotImplementedError  # never evaluated: the config tests only validate and build


class ToyPlugin:
    @occplug.hookimpl
    def occplug_register_components(self, registry: occplug.Registry) -> None:
        registry.add("encoder", "toy_encoder", ToyEncoder)
        registry.add("encoder", "other_encoder", OtherEncoder)
        registry.add("model", "toy_model", ToyModel)


class ClashingPlugin:
    @occplug.hookimpl
    def occplug_register_components(self, registry: occplug.Registry) -> None:
        registry.add("encoder", "toy_encoder", OtherEncoder)


class BrokenRegistration:
    @occplug.hookimpl
    def occplug_register_components(self, registry: occplug.Registry) -> None:
        registry.add("encoder", "half_done", OtherEncoder)
        raise RuntimeError("boom while registering")
