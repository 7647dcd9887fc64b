"""Helpers of the data tests."""

import builtins
import os
from typing import ClassVar

import pytest

from occplug.data.extensions import FrameTransform, LabelSource
from occplug.data.frame import FieldRule


@pytest.fixture
def touched(monkeypatch):
    """Every path the code under test stats or opens from now on (``os.stat``, ``os.open``, ``open``), as strings."""
    seen: list[str] = []
    real_stat, real_os_open, real_open = os.stat, os.open, builtins.open

    def stat(path, *args, **kwargs):
        seen.append(os.fsdecode(path) if not isinstance(path, int) else f"<fd {path}>")
        return real_stat(path, *args, **kwargs)

    def os_open(path, *args, **kwargs):
        seen.append(os.fsdecode(path))
        return real_os_open(path, *args, **kwargs)

    def open_(file, *args, **kwargs):
        seen.append(os.fsdecode(file) if not isinstance(file, int) else f"<fd {file}>")
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr(os, "stat", stat)
    monkeypatch.setattr(os, "open", os_open)
    monkeypatch.setattr(builtins, "open", open_)
    return seen


class ToyCameraCount(LabelSource):
    """Label source of the tests: ``extras["toy_ids"]`` = ``arange(frame_index + 1) + offset`` (a ragged field, padded)."""

    fields: ClassVar = {"toy_ids": FieldRule("pad", -1)}

    def __init__(self, offset: int = 0, class_names=()) -> None:
        self.offset = offset
        self.num_classes = len(class_names)

    def attach(self, frame):
        import torch

        frame.extras["toy_ids"] = torch.arange(frame.frame_index + 1) + self.offset
        frame.extras["toy_num_classes"] = self.num_classes
        return frame


class ToyTag(FrameTransform):
    """Frame transform of the tests: ``extras["toy_tag"]`` = ``[scale * frame_index, #adjacent]`` and images * 0."""

    def __init__(self, scale: float = 1.0) -> None:
        self.scale = scale

    def __call__(self, frame):
        import torch

        frame.extras["toy_tag"] = torch.tensor([self.scale * frame.frame_index, float(len(frame.adjacent))])
        frame.images = frame.images * 0
        return frame


@pytest.fixture
def toy_extensions(monkeypatch):
    """Registers label source ``toy_ids`` and transform ``toy_tag`` in the process registry, as a plugin would."""
    from occplug.plugins import get_registry
    from occplug.registry import Entry

    registry = get_registry()
    for kind, name, factory in (("label_source", "toy_ids", ToyCameraCount), ("transform", "toy_tag", ToyTag)):
        monkeypatch.setitem(registry._entries, (kind, name), Entry(kind, name, factory, "toy_data_plugin"))
    return registry
