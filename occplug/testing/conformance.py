"""The conformance check every registered component passes (timm/anomalib style)."""

from __future__ import annotations

import copy
import pickle
from typing import Any

import torch
from torch import Tensor, nn

from occplug import interfaces as I
from occplug.config.slots import component_params
from occplug.data.frame import Batch
from occplug.geometry import GridSpec
from occplug.kinds import KINDS, given_arguments
from occplug.metrics.base import OccMetric
from occplug.model import build_component
from occplug.plugins import get_registry

__all__ = ["CHECKED_KINDS", "check_component", "label_grid"]

#: Channels of the synthetic inputs fed to view transforms, scenes and heads.
IN_CHANNELS = 8


def label_grid(batch: Batch) -> GridSpec:
    """The grid of a tiny-world batch's labels (the ``tiny`` preset's grid)."""
    from occplug.data.synthetic import SyntheticDataModule

    grid = SyntheticDataModule(preset="tiny").grid
    if batch.voxel_labels is not None and tuple(batch.voxel_labels.shape[1:]) != grid.shape:
        raise ValueError(f"check_component expects a tiny-preset batch (labels {grid.shape})")
    return grid


def _finite(obj: Any, where: str) -> None:
    if isinstance(obj, Tensor):
        assert not obj.is_floating_point() or torch.isfinite(obj).all(), f"{where}: non-finite values"
    elif isinstance(obj, dict):
        for k, v in obj.items():
            _finite(v, f"{where}[{k}]")


def _has_grad(module: nn.Module, what: str) -> None:
    trainable = [p for p in module.parameters() if p.requires_grad]
    if trainable and all(p.grad is None or p.grad.abs().sum() == 0 for p in trainable):
        raise AssertionError(f"{what}: no parameter received a gradient")


def check_component(kind: str, name: str, spec: dict[str, Any] | None = None, *, batch: Batch) -> Any:
    """Build ``(kind, name)`` with ``spec`` on top of defaults and check it behaves as its kind promises.

    Common checks: no constructor parameter named ``type`` (configs reserve it), the object
    subclasses its kind's interface, it pickles (DDP spawn), forward is seeded-deterministic in
    eval mode, outputs are finite with the documented shapes, and gradients reach its parameters.
    ``batch`` is a tiny-world batch (``occplug.testing.make_tiny_batch``). Returns the component.
    """
    entry = get_registry().get(kind, name)
    if "type" in component_params(entry.factory):
        raise AssertionError(f"{kind} '{name}' has a constructor parameter named 'type', which configs reserve")
    grid = label_grid(batch)
    node: dict[str, Any] = {"type": name}
    if "grid" in component_params(entry.factory):
        node["grid"] = grid.to_dict()
    node.update(spec or {})
    # what a parent would pass: the kind's contract names the arguments, this table their test values
    values = {
        "in_channels": IN_CHANNELS,
        "image_stride": 4,
        "num_classes": 18,
        "free_label": 17,
        "grid": grid.to_dict(),
        "level_channels": [IN_CHANNELS],
        "level_strides": [4],
        "num_bins": 6,
        "out_channels": IN_CHANNELS,
    }
    defaults = {k: values[k] for k in given_arguments(kind, entry.factory) if k in values}
    torch.manual_seed(0)
    comp = build_component(kind, node, **defaults)
    base = KINDS[kind].interface()
    assert isinstance(comp, base), f"{kind} '{name}' is not a {base.__name__}"
    pickle.loads(pickle.dumps(comp))
    missing = [
        f for f in sorted(getattr(comp, "requires", ())) if f.startswith("pseudo_") and getattr(batch, f) is None
    ]
    if missing:  # a component that reads pseudo labels is checked on the same tiny frames with the world's own
        from .fixtures import make_tiny_batch

        batch = make_tiny_batch(len(batch), pseudo_labels="default")
    if kind in _CHECKS:
        _CHECKS[kind](comp, batch, grid)
    return comp


def _deterministic(module: nn.Module, fn: Any) -> Any:
    module.eval()
    first = fn(module)
    second = fn(copy.deepcopy(module))
    module.train()
    return first, second


def _inputs(component: nn.Module, batch: Batch, grid: GridSpec) -> tuple[Any, ...]:
    """The component's own conformance inputs (its interface's, unless it supplies its own)."""
    return type(component).conformance_inputs(batch, grid, IN_CHANNELS)


def _check_encoder(enc: I.ImageEncoder, batch: Batch, grid: GridSpec) -> None:
    assert isinstance(enc.out_channels, int) and isinstance(enc.stride, int), "encoder must set out_channels and stride"
    b, n, _, h, w = batch.images.shape
    inputs = _inputs(enc, batch, grid)
    first, second = _deterministic(enc, lambda m: I.feature_levels(m(*inputs)))
    channels, strides = enc.level_channels, enc.level_strides
    assert len(first) == len(channels) == len(strides), f"encoder gave {len(first)} levels, declares {len(channels)}"
    assert 0 <= enc.primary_level < len(first), f"primary_level {enc.primary_level} outside {len(first)} levels"
    assert (channels[enc.primary_level], strides[enc.primary_level]) == (enc.out_channels, enc.stride), (
        "the primary level must have out_channels and stride"
    )
    for level, (a, c, s) in enumerate(zip(first, channels, strides, strict=True)):
        assert a.shape == (b, n, c, h // s, w // s), f"encoder level {level}: {tuple(a.shape)}"
    for a, c in zip(first, second, strict=True):
        assert torch.equal(a, c), "encoder is not deterministic in eval mode"
        _finite(a, "encoder output")
    torch.stack([x.square().mean() for x in I.feature_levels(enc(*inputs))]).sum().backward()
    _has_grad(enc, "encoder")


def _check_point_encoder(enc: I.PointEncoder, batch: Batch, grid: GridSpec) -> None:
    assert isinstance(enc.out_channels, int) and isinstance(enc.grid, GridSpec), "point encoder sets out_channels, grid"
    inputs = _inputs(enc, batch, grid)
    first, second = _deterministic(enc, lambda m: m(*inputs))
    assert first.shape == (len(batch), enc.out_channels, *enc.grid.shape), f"point encoder output {tuple(first.shape)}"
    assert torch.equal(first, second), "point encoder is not deterministic in eval mode"
    _finite(first, "point encoder output")
    enc(*inputs).square().mean().backward()
    _has_grad(enc, "point encoder")


def _check_depth_net(net: I.DepthNet, batch: Batch, grid: GridSpec) -> None:
    inputs = _inputs(net, batch, grid)
    first, second = _deterministic(net, lambda m: m(*inputs))
    b, n, _, h, w = inputs[0].shape
    assert isinstance(first, I.DepthAndContext), "a depth net returns DepthAndContext"
    assert first.depth_logits.shape == (b, n, net.num_bins, h, w), f"depth logits {tuple(first.depth_logits.shape)}"
    assert first.context.shape == (b, n, net.out_channels, h, w), f"context {tuple(first.context.shape)}"
    assert torch.equal(first.depth_logits, second.depth_logits) and torch.equal(first.context, second.context), (
        "depth net is not deterministic in eval mode"
    )
    out = net(*inputs)
    (out.depth_logits.square().mean() + out.context.square().mean()).backward()
    assert inputs[0].grad is not None and inputs[0].grad.abs().sum() > 0, "no gradient reaches the image features"
    _has_grad(net, "depth net")


def _check_view_transform(vt: I.ViewTransform, batch: Batch, grid: GridSpec) -> None:
    inputs = _inputs(vt, batch, grid)
    first, second = _deterministic(vt, lambda m: m(*inputs).volume)
    assert torch.equal(first, second), "view transform is not deterministic in eval mode"
    lifted = vt(*inputs)
    b = len(batch)
    assert isinstance(lifted, I.Lifted), "a view transform returns Lifted"
    assert lifted.volume.shape[:2] == (b, vt.out_channels), f"volume shape {tuple(lifted.volume.shape)}"
    assert tuple(lifted.volume.shape[2:]) in (lifted.grid.shape, lifted.grid.shape[:2])
    if lifted.depth_probs is not None:
        assert lifted.depth_bins is not None and lifted.depth_probs.shape[2] == lifted.depth_bins.shape[0]
        assert torch.allclose(lifted.depth_probs.sum(2), torch.ones(()), atol=1e-4), "depth_probs must sum to 1"
    _finite(lifted.volume, "lifted volume")
    lifted.volume.square().mean().backward()
    feats = inputs[0]
    if isinstance(feats, Tensor) and feats.requires_grad:
        assert feats.grad is not None and feats.grad.abs().sum() > 0, "no gradient reaches the image features"
    _has_grad(vt, "view transform")


def _check_scene(rep: I.SceneRepresentation, batch: Batch, grid: GridSpec) -> None:
    inputs = _inputs(rep, batch, grid)
    first, second = _deterministic(rep, lambda m: m(*inputs).features)
    assert torch.equal(first, second), "scene is not deterministic in eval mode"
    scene = rep(*inputs)
    assert isinstance(scene, I.Scene), "a scene representation returns a Scene"
    points = grid.centers()[::3, ::3, ::2].reshape(1, -1, 3).expand(len(batch), -1, -1)
    out = scene.sample(points)
    assert out.shape == (len(batch), points.shape[1], scene.channels), f"sample shape {tuple(out.shape)}"
    _finite(out, "scene sample")
    out.square().mean().backward()
    _has_grad(rep, "scene")


def _check_head(head: I.Head, batch: Batch, grid: GridSpec) -> None:
    inputs = _inputs(head, batch, grid)
    scene = inputs[0]
    first, second = _deterministic(head, lambda m: m(*inputs))
    assert isinstance(first, dict) and all(isinstance(v, Tensor) for v in first.values()), (
        "a head returns dict[str, Tensor]"
    )
    for key in first:
        assert torch.equal(first[key], second[key]), f"head output '{key}' is not deterministic in eval mode"
    _finite(first, "head output")
    reads = bool(getattr(head, "reads", ())) or head.reads_outputs
    if isinstance(head, I.OccupancyHead) and not reads:  # a reading head is evaluated from its forward logits
        head.eval()
        logits = head.occupancy_logits(scene, grid)
        assert logits.shape == (len(batch), head.num_classes, *grid.shape), f"occupancy_logits {tuple(logits.shape)}"
        assert torch.allclose(logits, head(*inputs)["logits"], atol=1e-5), "occupancy_logits != forward logits"
        if head.queryable:  # queries at voxel centres agree with the voxel logits; t != 0 only for temporal heads
            idx = torch.tensor([[1, 2, 3], [5, 0, 1]])
            pts = grid.index_to_coord(idx)[None].expand(len(batch), -1, -1)
            result = head.query(scene, pts)
            assert isinstance(result, I.QueryResult), f"query returned a {type(result).__name__}, not a QueryResult"
            expected = logits[:, :, idx[:, 0], idx[:, 1], idx[:, 2]].transpose(1, 2)
            queried = result.logits(head.free_label)
            assert torch.allclose(queried, expected, atol=1e-4), "query at voxel centres != occupancy logits"
            if not head.temporal:
                try:
                    head.query(scene, pts, torch.full(pts.shape[:2], 0.5))
                except ValueError:
                    pass
                else:
                    raise AssertionError("a head that is not temporal must reject queries at t != 0 (ValueError)")
        head.train()
    out = head(*inputs)
    torch.stack([v.float().square().mean() for v in out.values() if v.is_floating_point()]).sum().backward()
    _has_grad(head, "head")


def _check_supervision(source: I.SupervisionSource, batch: Batch, grid: GridSpec) -> None:
    from occplug.model import OccModel

    model = OccModel(
        encoder={"type": "small_cnn", "out_channels": IN_CHANNELS, "width": 8, "stride": 4},
        # lss: it also predicts depth distributions, which depth supervision reads
        view_transform={
            "type": "lss",
            "grid": grid.to_dict(),
            "out_channels": IN_CHANNELS,
            "hidden": 0,
            "depth_bins": [1.0, 41.0, 2.0],
        },
        scene={"type": "dense_voxels", "out_channels": IN_CHANNELS, "num_blocks": 0},
        heads={"occupancy": {"type": "voxel_classifier", "hidden": 8}},
        supervision={},
        grid=grid.to_dict(),
    )
    own = type(source).conformance_outputs(batch, grid, IN_CHANNELS)
    outputs = model(batch) if own is None else own
    losses = source(batch, outputs)
    assert isinstance(losses, dict) and losses, "a supervision source returns a non-empty dict of losses"
    for key, value in losses.items():
        assert value.dim() == 0 and torch.isfinite(value), f"loss '{key}' must be a finite scalar"
    total = torch.stack(list(losses.values())).sum()
    assert total.requires_grad, "the losses carry no gradient"
    total.backward()
    if own is None:
        _has_grad(model, "model under this supervision")


def _check_metric(metric: OccMetric, batch: Batch, grid: GridSpec) -> None:
    assert isinstance(metric, OccMetric)
    batch.require("voxel_labels", by="the metric conformance check")
    metric.update(batch.voxel_labels.long(), batch)
    perfect = metric.compute()
    assert isinstance(perfect, dict) and perfect, "compute() returns a non-empty dict"
    for key, value in perfect.items():
        assert value.dim() == 0, f"metric result '{key}' must be a scalar"
    metric.reset()


_CHECKS = {
    "encoder": _check_encoder,
    "point_encoder": _check_point_encoder,
    "view_transform": _check_view_transform,
    "depth_net": _check_depth_net,
    "scene": _check_scene,
    "head": _check_head,
    "supervision": _check_supervision,
    "metric": _check_metric,
}
#: Kinds whose components the conformance check runs (the others: data, model, callback, are
#: exercised by the config sweep, which fits every shipped recipe).
CHECKED_KINDS: tuple[str, ...] = tuple(k for k in KINDS if k in _CHECKS)
