"""The conformance check every registered component passes (timm/anomalib style)."""

from __future__ import annotations

import copy
import inspect
import pickle
from typing import Any

import torch
from torch import Tensor, nn

from occplug import interfaces as I
from occplug.config.slots import component_params
from occplug.data.frame import Batch
from occplug.geometry import GridSpec
from occplug.model import build_component
from occplug.plugins import get_registry

__all__ = ["check_component", "default_spec"]


def default_spec(kind: str, name: str, batch: Batch, grid: GridSpec) -> dict[str, Any]:
    """A node ``{type: name}`` plus values for required arguments the registry knows how to fill."""
    entry = get_registry().get(kind, name)
    params = component_params(entry.factory)
    if "type" in params:
        raise AssertionError(f"{kind} '{name}' has a constructor parameter named 'type', which configs reserve")
    spec: dict[str, Any] = {"type": name}
    if "grid" in params:
        spec["grid"] = grid.to_dict()
    return spec


def _finite(obj: Any, where: str) -> None:
    if isinstance(obj, Tensor):
        if obj.is_floating_point() and not torch.isfinite(obj).all():
            raise AssertionError(f"{where}: non-finite values")
    elif isinstance(obj, dict):
        for k, v in obj.items():
            _finite(v, f"{where}[{k}]")


def _seeded(fn: Any, seed: int = 0) -> Any:
    torch.manual_seed(seed)
    return fn()


def check_component(kind: str, name: str, spec: dict[str, Any] | None = None, *, batch: Batch) -> Any:
    """Build ``(kind, name)`` with ``spec`` on top of defaults and check it behaves.

    Checks: it subclasses its kind's interface; it is picklable (DDP spawn); encoders, view
    transforms, scenes and heads run forward on ``batch`` with the documented output types and
    shapes, finite values and seeded determinism; gradients reach every trainable parameter that
    the output depends on. Returns the built component.
    """
    grid = GridSpec(range=(-16, -16, -1, 16, 16, 5.4), voxel_size=0.8)
    if batch.voxel_labels is not None:
        grid = GridSpec(range=grid.range, voxel_size=_voxel_size_for(batch, grid))
    node = {**default_spec(kind, name, batch, grid), **(spec or {})}
    make = {
        "encoder": lambda: build_component("encoder", node),
        "view_transform": lambda: build_component("view_transform", node, in_channels=8, image_stride=4),
        "scene": lambda: build_component("scene", node, in_channels=8),
        "head": lambda: build_component("head", node, in_channels=8, num_classes=18),
        "supervision": lambda: build_component("supervision", node),
        "metric": lambda: build_component("metric", node, num_classes=18),
    }
    if kind not in make:
        return get_registry().build(kind, node)
    comp = _seeded(make[kind])
    pickle.loads(pickle.dumps(comp))
    if kind == "encoder":
        _check_encoder(comp, batch, make[kind])
    elif kind == "view_transform":
        _check_view_transform(comp, batch)
    return comp


def _voxel_size_for(batch: Batch, grid: GridSpec) -> float:
    x = batch.voxel_labels.shape[1]
    return (grid.range[3] - grid.range[0]) / x


def _check_encoder(enc: I.ImageEncoder, batch: Batch, make: Any) -> None:
    assert isinstance(enc.out_channels, int) and isinstance(enc.stride, int), "encoder must set out_channels and stride"
    enc.eval()
    out = enc(batch.images)
    b, n, _, h, w = batch.images.shape
    assert out.shape == (b, n, enc.out_channels, h // enc.stride, w // enc.stride), f"encoder output {tuple(out.shape)}"
    _finite(out, "encoder output")
    again = copy.deepcopy(enc)(batch.images)
    assert torch.equal(out, again), "encoder is not deterministic in eval mode"
    enc.train()
    _check_grads(enc, enc(batch.images).square().mean())


def _check_view_transform(vt: I.ViewTransform, batch: Batch) -> None:
    b, n, _, h, w = batch.images.shape
    feats = torch.randn(b, n, 8, h // 4, w // 4, requires_grad=True)
    lifted = vt(feats, batch)
    assert isinstance(lifted, I.Lifted), "a view transform returns Lifted"
    assert lifted.volume.shape[:2] == (b, vt.out_channels), f"volume shape {tuple(lifted.volume.shape)}"
    assert tuple(lifted.volume.shape[2:]) in (lifted.grid.shape, lifted.grid.shape[:2])
    _finite(lifted.volume, "lifted volume")
    lifted.volume.square().mean().backward()
    assert feats.grad is not None and feats.grad.abs().sum() > 0, "no gradient reaches the image features"


def _check_grads(module: nn.Module, loss: Tensor) -> None:
    loss.backward()
    trainable = [(n, p) for n, p in module.named_parameters() if p.requires_grad]
    without = [n for n, p in trainable if p.grad is None]
    if trainable and len(without) == len(trainable):
        raise AssertionError(f"no parameter of {type(module).__name__} received a gradient")


def signature_summary(factory: Any) -> str:
    """``name(arg: type = default, ...)`` of a factory, for docs and error messages."""
    return f"{getattr(factory, '__name__', factory)}{inspect.signature(factory)}"
