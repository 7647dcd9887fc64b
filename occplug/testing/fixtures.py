"""Pytest fixtures for occplug and its plugins."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack

import pytest

from occplug.data.frame import Batch, collate_frames
from occplug.plugins import isolated
from occplug.registry import Registry

__all__ = ["isolated_registry", "make_tiny_batch", "tiny_batch"]

_TINY_CACHE: dict[tuple, Batch] = {}


def make_tiny_batch(batch_size: int = 2, split: str = "train", adjacent_offsets: Sequence[int] = ()) -> Batch:
    """A batch of the first frames of the tiny synthetic world (seeded, CPU, cached per process)."""
    key = (batch_size, split, tuple(adjacent_offsets))
    if key not in _TINY_CACHE:
        from occplug.data.synthetic import SyntheticDataModule

        dm = SyntheticDataModule(preset="tiny", adjacent_offsets=list(adjacent_offsets), batch_size=batch_size)
        ds = dm.dataset(split)
        _TINY_CACHE[key] = collate_frames([ds[i] for i in range(batch_size)])
    return _TINY_CACHE[key]


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
