"""A plugin that fails to load is named where it matters: in an unknown ``type:`` and in one ``fit`` warning line."""

from __future__ import annotations

from importlib import metadata
from pathlib import Path

import pytest
from toy_plugin import BrokenRegistration

from occplug import plugins
from occplug.cli import main
from occplug.registry import UnknownComponentError

ROOT = Path(__file__).resolve().parents[2]
PROBLEM = "failed to import: ImportError: occplug_broken needs torch_scatter"


@pytest.fixture
def broken_plugin(tmp_path, monkeypatch):
    """An installed entry point ``broken`` whose module raises ImportError at import."""
    (tmp_path / "occplug_broken.py").write_text("raise ImportError('occplug_broken needs torch_scatter')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    entry_point = metadata.EntryPoint(name="broken", value="occplug_broken", group="occplug")
    monkeypatch.setattr(plugins, "_entry_points", lambda: [entry_point])
    plugins.reset()
    yield
    plugins.reset()


def test_unknown_type_names_the_plugin_that_failed_to_import(broken_plugin):
    report = next(r for r in plugins.plugin_reports() if r.name == "broken")
    assert report.failed_to == "import" and report.problem == PROBLEM
    with pytest.raises(UnknownComponentError) as info:
        plugins.get_registry().get("head", "tiny_mlp")
    assert str(info.value).startswith(f"no head named 'tiny_mlp' (plugin 'broken' {PROBLEM}); available: ")
    assert "voxel_classifier" in str(info.value)


def test_fit_prints_one_warning_line_naming_the_broken_plugin(broken_plugin, tmp_path, capsys):
    run = tmp_path / "run"
    code = main(["fit", "-c", str(ROOT / "configs" / "baseline.yaml"), "model.heads.occupancy.type=tiny_mlp",
                 "--run-dir", str(run)])
    assert code == 2 and not run.exists()
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines[0] == (f"warning: plugin 'broken' {PROBLEM} (its components are unavailable; "
                        "`occplug plugins` shows details)")
    error = f"error: model.heads.occupancy.type: no head named 'tiny_mlp' (plugin 'broken' {PROBLEM})"
    assert lines[1].startswith(error)
    assert len(lines) == 2


def test_no_warning_when_every_plugin_loads(monkeypatch):
    monkeypatch.setattr(plugins, "_entry_points", list)
    plugins.reset()
    try:
        assert plugins.broken_plugins_warning() is None
        assert plugins.get_registry().broken_plugins == {}
        with pytest.raises(UnknownComponentError, match=r"^no head named 'tiny_mlp'; available: "):
            plugins.get_registry().get("head", "tiny_mlp")
    finally:
        plugins.reset()


def test_a_plugin_whose_hook_raises_failed_to_register(isolated_registry):
    registry = isolated_registry(plugins=[("half", BrokenRegistration())])
    assert registry.broken_plugins == {"half": "failed to register: RuntimeError: boom while registering"}
    assert not registry.has("encoder", "half_done")
