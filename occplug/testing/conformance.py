"""The conformance check every registered component passes (timm/anomalib style).

What is common to every kind (no ``type`` parameter, the interface subclassed, pickling, what a parent gives) is
checked here; what a kind promises is checked by its interface's ``check_conformance``, beside the contract.
"""

from __future__ import annotations

import inspect
import pickle
from typing import Any

import torch

from occplug.context import RunContext
from occplug.data.classes import OCC3D_CLASSES, class_groups
from occplug.data.frame import Batch
from occplug.geometry import GridSpec
from occplug.interfaces.checks import CHECK_CHANNELS
from occplug.kinds import KINDS, given_arguments
from occplug.model import OccModel
from occplug.plugins import get_registry
from occplug.slots import component_params

__all__ = ["CHECKED_KINDS", "check_component", "label_grid"]


def label_grid(batch: Batch) -> GridSpec:
    """The grid of a tiny-world batch's labels (the ``tiny`` preset's grid)."""
    from occplug.data.synthetic import SyntheticDataModule

    grid = SyntheticDataModule(preset="tiny").grid
    if batch.voxel_labels is not None and tuple(batch.voxel_labels.shape[1:]) != grid.shape:
        raise ValueError(f"check_component expects a tiny-preset batch (labels {grid.shape})")
    return grid


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
        "in_channels": CHECK_CHANNELS,
        "image_stride": 4,
        "num_classes": 18,
        "free_label": 17,
        "grid": grid.to_dict(),
        "level_channels": [CHECK_CHANNELS],
        "level_strides": [4],
        "num_bins": 6,
        "out_channels": CHECK_CHANNELS,
        "scene_downsample": 2,  # a head or source that declares it reads a scene at half the grid's resolution
    }
    defaults = {k: values[k] for k in given_arguments(kind, entry.factory) if k in values}
    torch.manual_seed(0)
    comp = get_registry().build(kind, node, context=tiny_context(grid), **defaults)
    base = KINDS[kind].interface()
    assert isinstance(comp, base), f"{kind} '{name}' is not a {base.__name__}"
    pickle.loads(pickle.dumps(comp))
    missing = [
        f for f in sorted(getattr(comp, "requires", ())) if f.startswith("pseudo_") and getattr(batch, f) is None
    ]
    if missing:  # a component that reads pseudo labels is checked on the same tiny frames with the world's own
        from .fixtures import make_tiny_batch

        batch = make_tiny_batch(len(batch), pseudo_labels="default")
    check = getattr(base, "check_conformance", None)  # the kind's own check, on its interface
    if check is not None:
        # a check that trains the component through a model (supervision) is given a small one
        needs_model = "model" in inspect.signature(check).parameters
        check(comp, batch, grid, **({"model": small_model(grid)} if needs_model else {}))
    return comp


def tiny_context(grid: GridSpec) -> RunContext:
    """The run context a parent hands a checked component: ``grid``, the Occ3D classes (``free`` = 17)."""
    return RunContext(
        grid=grid,
        class_names=OCC3D_CLASSES,
        free_label=17,
        ignore_label=255,
        class_groups=class_groups(OCC3D_CLASSES) or {},
        registry=get_registry(),
    )


def small_model(grid: GridSpec) -> OccModel:
    """A small LSS model on ``grid`` (small CNN, ``lss``, dense voxels, a voxel classifier), whose outputs the
    supervision check trains a source on."""
    return tiny_context(grid).build(
        "model",
        {"type": "occ_model"},
        encoder={"type": "small_cnn", "out_channels": CHECK_CHANNELS, "width": 8, "stride": 4},
        # lss: it also predicts depth distributions, which depth supervision reads
        view_transform={
            "type": "lss",
            "grid": grid.to_dict(),
            "out_channels": CHECK_CHANNELS,
            "hidden": 0,
            "depth_bins": [1.0, 41.0, 2.0],
        },
        scene={"type": "dense_voxels", "out_channels": CHECK_CHANNELS, "num_blocks": 0},
        heads={"occupancy": {"type": "voxel_classifier", "hidden": 8}},
        supervision={},
        grid=grid.to_dict(),
        class_names=list(OCC3D_CLASSES),
    )


#: Kinds whose components the conformance check runs: those whose interface defines ``check_conformance`` (the
#: others: data, model, callback, transform, label_source, are exercised by the config sweep, which fits every
#: shipped recipe).
CHECKED_KINDS: tuple[str, ...] = tuple(k for k, kind in KINDS.items() if hasattr(kind.interface(), "check_conformance"))
