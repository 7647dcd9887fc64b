"""Helpers of the data tests."""

import builtins
import os

import pytest


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
