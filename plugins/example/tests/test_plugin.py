"""Tests a plugin author writes: registration via the installed entry point, conformance, a short fit."""

import json

import pytest

from occplug.testing import check_component, make_tiny_batch, run_config


def test_entry_point_registers_the_head(isolated_registry):
    registry = isolated_registry(entry_points=["example"])  # fails if pyproject lacks the entry point
    entry = registry.get("head", "tiny_mlp")
    assert entry.plugin == "example" and entry.distribution == "occplug-example"


@pytest.mark.parametrize("hidden", [8, 32])
def test_tiny_mlp_conforms(isolated_registry, hidden):
    isolated_registry(entry_points=["example"])
    check_component("head", "tiny_mlp", {"hidden": hidden}, batch=make_tiny_batch())


def test_shipped_config_trains(isolated_registry, tmp_path):
    isolated_registry(entry_points=["example"])
    metrics = run_config("example/tiny", run_dir=tmp_path / "run")
    assert "mIoU" in metrics
    assert "mIoU" in json.loads((tmp_path / "run" / "metrics.json").read_text())
