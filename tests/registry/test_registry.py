import json
from importlib import metadata

import pytest
from toy_plugin import BrokenRegistration, ClashingPlugin, OtherEncoder, ToyEncoder, ToyPlugin

from occplug import plugins
from occplug.cli import main
from occplug.registry import ComponentClashError, Registry, UnknownComponentError


def test_add_get_and_provenance(isolated_registry):
    reg = isolated_registry(plugins=[("toy", ToyPlugin())])
    entry = reg.get("encoder", "toy_encoder")
    assert entry.factory is ToyEncoder and entry.plugin == "toy"
    assert entry.summary == "A toy encoder with typed arguments."
    assert "toy_encoder" in reg.names("encoder", "toy_*")
    assert reg.get("encoder", "small_cnn").plugin == "occplug"  # built-ins register through the same hook


def test_unknown_name_lists_available_and_closest(isolated_registry):
    reg = isolated_registry(plugins=[("toy", ToyPlugin())])
    with pytest.raises(UnknownComponentError) as err:
        reg.get("encoder", "toy_encodr")
    msg = str(err.value)
    assert "no encoder named 'toy_encodr'" in msg and "did you mean 'toy_encoder'?" in msg
    assert "other_encoder" in msg and "small_cnn" in msg
    assert not msg.startswith("'")  # LookupError, not KeyError's quoted str()


def test_clash_between_two_plugins_names_both():
    reg = Registry()
    reg.current_plugin, reg.current_distribution = "first", "occplug-first"
    reg.add("encoder", "same", ToyEncoder)
    reg.current_plugin, reg.current_distribution = "second", "occplug-second"
    with pytest.raises(ComponentClashError) as err:
        reg.add("encoder", "same", OtherEncoder)
    msg = str(err.value)
    assert "first" in msg and "occplug-first" in msg and "second" in msg and "occplug-second" in msg


def test_clash_through_plugin_manager(isolated_registry):
    with pytest.raises(ComponentClashError, match="plugin 'toy' and plugin 'clash'"):
        isolated_registry(plugins=[("toy", ToyPlugin()), ("clash", ClashingPlugin())])


def test_bad_kind_and_name_rejected():
    reg = Registry()
    with pytest.raises(ValueError, match="unknown component kind 'decoder'"):
        reg.add("decoder", "x", ToyEncoder)
    with pytest.raises(ValueError, match="snake_case"):
        reg.add("encoder", "BadName", ToyEncoder)


def test_broken_registration_is_reported_and_dropped(isolated_registry):
    reg = isolated_registry(plugins=[("broken", BrokenRegistration()), ("toy", ToyPlugin())])
    assert ("encoder", "half_done") not in reg  # no half-registered plugin
    assert ("encoder", "toy_encoder") in reg
    report = {r.name: r for r in plugins.plugin_reports()}["broken"]
    assert "boom while registering" in report.error


def test_plugin_that_fails_to_import_does_not_break_others(monkeypatch, capsys):
    broken = metadata.EntryPoint(name="broken", value="occplug_no_such_module_xyz", group="occplug")
    monkeypatch.setattr(plugins, "_entry_points", lambda: [broken])
    plugins.reset()
    try:
        assert main(["plugins", "--json"]) == 0
        data = json.loads(capsys.readouterr().out)
        by_name = {p["name"]: p for p in data}
        assert "ModuleNotFoundError" in by_name["broken"]["error"]
        assert "small_cnn" in by_name["occplug"]["components"]["encoder"]
        assert main(["plugins"]) == 0
        assert "ERROR: ModuleNotFoundError" in capsys.readouterr().out
    finally:
        plugins.reset()


def test_disable_switch(monkeypatch):
    ep = metadata.EntryPoint(name="toy", value="toy_plugin:ToyPlugin", group="occplug")
    monkeypatch.setattr(plugins, "_entry_points", lambda: [ep])
    monkeypatch.setenv("OCCPLUG_DISABLE_PLUGINS", "toy")
    plugins.reset()
    try:
        assert "toy" not in {r.name for r in plugins.plugin_reports()}
    finally:
        plugins.reset()


def test_isolated_registry_requires_installed_entry_point(isolated_registry):
    with pytest.raises(plugins.PluginLoadError, match="no installed entry point named nope"):
        isolated_registry(entry_points=["nope"])


def test_plugins_json_lists_builtin_components(capsys):
    assert main(["plugins", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    core = next(p for p in data if p["name"] == "occplug")
    assert core["version"] == metadata.version("occplug") and core["error"] is None
    assert set(core["components"]) >= {
        "encoder",
        "view_transform",
        "scene",
        "head",
        "supervision",
        "data",
        "metric",
        "model",
    }
    assert {"lss", "backward_projection"} <= set(core["components"]["view_transform"])


def test_plugins_unknown_kind_exits_2(capsys):
    assert main(["plugins", "--kind", "decoder"]) == 2
    assert "unknown kind" in capsys.readouterr().err
