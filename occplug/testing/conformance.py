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
from occplug.metrics.base import OccMetric
from occplug.model import KIND_INTERFACES, build_component
from occplug.plugins import get_registry

__all__ = ["check_component", "label_grid"]

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
    defaults = {
        "view_transform": {"in_channels": IN_CHANNELS, "image_stride": 4},
        "scene": {"in_channels": IN_CHANNELS},
        "head": {"in_channels": IN_CHANNELS, "num_classes": 18},
        "metric": {"num_classes": 18},
    }.get(kind, {})
    torch.manual_seed(0)
    comp = build_component(kind, node, **defaults)
    if kind in KIND_INTERFACES:
        assert isinstance(comp, KIND_INTERFACES[kind]), f"{kind} '{name}' is not a {KIND_INTERFACES[kind].__name__}"
    pickle.loads(pickle.dumps(comp))
    checks = {
        "encoder": _check_encoder,
        "view_transform": _check_view_transform,
        "scene": _check_scene,
        "head": _check_head,
        "supervision": _check_supervision,
        "metric": _check_metric,
    }
    if kind in checks:
        checks[kind](comp, batch, grid)
    return comp


def _deterministic(module: nn.Module, fn: Any) -> Any:
    module.eval()
    first = fn(module)
    second = fn(copy.deepcopy(module))
    module.train()
    return first, second


def _check_encoder(enc: I.ImageEncoder, batch: Batch, grid: GridSpec) -> None:
    assert isinstance(enc.out_channels, int) and isinstance(enc.stride, int), "encoder must set out_channels and stride"
    b, n, _, h, w = batch.images.shape
    first, second = _deterministic(enc, lambda m: m(batch.images))
    assert first.shape == (b, n, enc.out_channels, h // enc.stride, w // enc.stride), f"encoder output {tuple(first.shape)}"
    assert torch.equal(first, second), "encoder is not deterministic in eval mode"
    _finite(first, "encoder output")
    enc(batch.images).square().mean().backward()
    _has_grad(enc, "encoder")


def _check_view_transform(vt: I.ViewTransform, batch: Batch, grid: GridSpec) -> None:
    b, n, _, h, w = batch.images.shape
    feats = torch.randn(b, n, IN_CHANNELS, h // 4, w // 4, generator=torch.Generator().manual_seed(0), requires_grad=True)
    first, second = _deterministic(vt, lambda m: m(feats, batch).volume)
    assert torch.equal(first, second), "view transform is not deterministic in eval mode"
    lifted = vt(feats, batch)
    assert isinstance(lifted, I.Lifted), "a view transform returns Lifted"
    assert lifted.volume.shape[:2] == (b, vt.out_channels), f"volume shape {tuple(lifted.volume.shape)}"
    assert tuple(lifted.volume.shape[2:]) in (lifted.grid.shape, lifted.grid.shape[:2])
    if lifted.depth_probs is not None:
        assert lifted.depth_bins is not None and lifted.depth_probs.shape[2] == lifted.depth_bins.shape[0]
        assert torch.allclose(lifted.depth_probs.sum(2), torch.ones(()), atol=1e-4), "depth_probs must sum to 1"
    _finite(lifted.volume, "lifted volume")
    lifted.volume.square().mean().backward()
    assert feats.grad is not None and feats.grad.abs().sum() > 0, "no gradient reaches the image features"
    _has_grad(vt, "view transform")


def _lifted(grid: GridSpec, batch: Batch) -> I.Lifted:
    vol = torch.randn(len(batch), IN_CHANNELS, *grid.shape, generator=torch.Generator().manual_seed(0))
    return I.Lifted(volume=vol, grid=grid)


def _check_scene(rep: I.SceneRepresentation, batch: Batch, grid: GridSpec) -> None:
    lifted = _lifted(grid, batch)
    first, second = _deterministic(rep, lambda m: m(lifted, batch).features)
    assert torch.equal(first, second), "scene is not deterministic in eval mode"
    scene = rep(lifted, batch)
    assert isinstance(scene, I.Scene), "a scene representation returns a Scene"
    points = grid.centers()[::3, ::3, ::2].reshape(1, -1, 3).expand(len(batch), -1, -1)
    out = scene.sample(points)
    assert out.shape == (len(batch), points.shape[1], scene.channels), f"sample shape {tuple(out.shape)}"
    _finite(out, "scene sample")
    out.square().mean().backward()
    _has_grad(rep, "scene")


def _check_head(head: I.Head, batch: Batch, grid: GridSpec) -> None:
    from occplug.components import DenseVoxelScene

    scene = DenseVoxelScene(_lifted(grid, batch).volume, grid)
    first, second = _deterministic(head, lambda m: m(scene, batch))
    assert isinstance(first, dict) and all(isinstance(v, Tensor) for v in first.values()), "a head returns dict[str, Tensor]"
    for key in first:
        assert torch.equal(first[key], second[key]), f"head output '{key}' is not deterministic in eval mode"
    _finite(first, "head output")
    if isinstance(head, I.OccupancyHead):
        head.eval()
        logits = head.occupancy_logits(scene, grid)
        assert logits.shape == (len(batch), head.num_classes, *grid.shape), f"occupancy_logits {tuple(logits.shape)}"
        assert torch.allclose(logits, head(scene, batch)["logits"], atol=1e-5), "occupancy_logits != forward logits"
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
    out = head(scene, batch)
    torch.stack([v.float().square().mean() for v in out.values() if v.is_floating_point()]).sum().backward()
    _has_grad(head, "head")


def _check_supervision(source: I.SupervisionSource, batch: Batch, grid: GridSpec) -> None:
    from occplug.model import OccModel

    model = OccModel(
        encoder={"type": "small_cnn", "out_channels": IN_CHANNELS, "width": 8, "stride": 4},
        # lss: it also predicts depth distributions, which depth supervision reads
        view_transform={"type": "lss", "grid": grid.to_dict(), "out_channels": IN_CHANNELS, "hidden": 0,
                        "depth_bins": [1.0, 41.0, 2.0]},
        scene={"type": "dense_voxels", "out_channels": IN_CHANNELS, "num_blocks": 0},
        heads={"occupancy": {"type": "voxel_classifier", "hidden": 8}},
        supervision={},
        grid=grid.to_dict(),
    )
    outputs = model(batch)
    losses = source(batch, outputs)
    assert isinstance(losses, dict) and losses, "a supervision source returns a non-empty dict of losses"
    for key, value in losses.items():
        assert value.dim() == 0 and torch.isfinite(value), f"loss '{key}' must be a finite scalar"
    torch.stack(list(losses.values())).sum().backward()
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
