"""Fixtures of the picture tests: the Occ3D palette, a small grid, the tiny synthetic world."""

from __future__ import annotations

import pytest
from viz_helpers import FREE, small_grid

from occplug.data.classes import OCC3D_CLASSES
from occplug.geometry import GridSpec
from occplug.viz.style import Palette


@pytest.fixture(scope="session")
def palette() -> Palette:
    """The Occ3D-nuScenes palette (free 17, ignore 255)."""
    return Palette.for_classes(OCC3D_CLASSES, FREE, 255)


@pytest.fixture(scope="session")
def grid() -> GridSpec:
    return small_grid()


@pytest.fixture(scope="session")
def tiny_dm():
    from occplug.data.synthetic import SyntheticDataModule

    return SyntheticDataModule(preset="tiny")


@pytest.fixture(scope="session")
def tiny_frame(tiny_dm):
    return tiny_dm.dataset("val")[0]
