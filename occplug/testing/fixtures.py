"""Pytest fixtures for occplug and its plugins."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack
from typing import Any

import pytest
import torch
from torch import Tensor

from occplug.data.frame import Batch, collate_frames
from occplug.plugins import isolated
from occplug.registry import Registry

__all__ = ["hand_batch", "isolated_registry", "label_batch", "make_tiny_batch", "tiny_batch"]

_TINY_CACHE: dict[tuple, Batch] = {}


def make_tiny_batch(
    batch_size: int = 2,
    split: str = "train",
    adjacent_offsets: Sequence[int] = (),
    pseudo_labels: str | dict[str, Any] | None = None,
) -> Batch:
    """A batch of the first frames of the tiny synthetic world (seeded, CPU, cached per process).

    ``pseudo_labels``: a synthetic realism (``perfect``, ``default``, ``noisy``, or a knob mapping such as
    ``{"preset": "default", "sky_as_free": True}``) to fill ``pseudo_depth``, ``pseudo_semantics`` and
    ``pseudo_features``; ``None``: none.
    """
    key = (batch_size, split, tuple(adjacent_offsets), repr(pseudo_labels))
    if key not in _TINY_CACHE:
        from occplug.data.synthetic import SyntheticDataModule

        dm = SyntheticDataModule(
            preset="tiny",
            adjacent_offsets=list(adjacent_offsets),
            batch_size=batch_size,
            pseudo_labels=None if pseudo_labels is None else {"synthetic": pseudo_labels},
        )
        ds = dm.dataset(split)
        _TINY_CACHE[key] = collate_frames([ds[i] for i in range(batch_size)])
    return _TINY_CACHE[key]


def hand_batch(batch_size: int, cameras: int = 1, image_hw: tuple[int, int] = (2, 2), **fields: Any) -> Batch:
    """A Batch built by hand: ``cameras`` placeholder cameras (identity calibration, black images) and
    empty sample fields, replaced by any ``fields`` given (``images``, ``intrinsics``, ``points`` ...)."""
    b, n = batch_size, cameras
    base: dict[str, Any] = dict(
        images=torch.zeros(b, n, 3, *image_hw),
        intrinsics=torch.eye(3).expand(b, n, 3, 3),
        cam_to_ego=torch.eye(4).expand(b, n, 4, 4),
        img_aug=torch.eye(3).expand(b, n, 3, 3),
        ego_to_global=torch.eye(4, dtype=torch.float64).expand(b, 4, 4),
        timestamp=torch.zeros(b, dtype=torch.float64),
        frame_index=torch.zeros(b, dtype=torch.int64),
        has_voxel_labels=torch.ones(b, dtype=torch.bool),
        is_sequence_start=torch.ones(b, dtype=torch.bool),
        scene=["s"] * b,
        token=[f"t{i}" for i in range(b)],
    )
    return Batch(**{**base, **fields})


def label_batch(labels: Tensor, image_hw: tuple[int, int] = (2, 2), **fields: Any) -> Batch:
    """A Batch of ``labels`` ``(B, X, Y, Z)`` with one placeholder camera, plus any other fields given
    (masks, ``has_voxel_labels``, origins ...): what a metric or supervision test needs, built by hand."""
    return hand_batch(labels.shape[0], image_hw=image_hw, **{"voxel_labels": labels, **fields})


@pytest.fixture
def tiny_batch() -> Batch:
    """Two frames of the tiny synthetic world, collated."""
    return make_tiny_batch()


@pytest.fixture
def isolated_registry() -> Iterator[Callable[..., Registry]]:
    """``isolated_registry(entry_points=[...], plugins=[(name, module)])`` -> Registry.

    Builds a plugin manager with autoload off: the built-ins plus only the named installed entry
    points (read from installed metadata, so the test proves the entry point exists) and plugin
    objects. It is the process-wide registry until the test ends.
    """
    with ExitStack() as stack:

        def make(entry_points: Sequence[str] = (), plugins: Sequence[tuple[str, object]] = ()) -> Registry:
            return stack.enter_context(isolated(entry_points, plugins))

        yield make
