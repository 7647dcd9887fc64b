"""Meta-tests: every hook is documented in docs/plugins.md and has a docstring with versionadded."""

import inspect
from pathlib import Path

from occplug import hookspecs
from occplug.kinds import KINDS

DOC = (Path(__file__).resolve().parents[2] / "docs" / "plugins.md").read_text()


def hook_names():
    return [n for n, f in vars(hookspecs).items() if n.startswith("occplug_") and inspect.isfunction(f)]


def test_every_hookspec_is_documented_with_its_signature():
    names = hook_names()
    assert names == ["occplug_register_components", "occplug_config_dir"] or set(names) == {
        "occplug_register_components",
        "occplug_config_dir",
    }
    for name in names:
        params = ", ".join(inspect.signature(getattr(hookspecs, name)).parameters)
        assert f"### `{name}({params})`" in DOC, f"docs/plugins.md lacks a section for {name}({params})"
        assert ".. versionadded::" in inspect.getdoc(getattr(hookspecs, name))


def test_hook_register_components_via_builtin(isolated_registry):
    registry = isolated_registry()
    kinds = {e.kind for e in registry.entries()}
    # the built-ins fill every kind except frame transforms, which only plugins (and tests) register
    # (the one built-in label source is teacher_pseudo_labels, which phases attach)
    assert set(KINDS) - kinds == {"transform"} and kinds <= set(KINDS)
    assert all(e.plugin == "occplug" for e in registry.entries())


def test_hook_config_dir_addresses_core_configs():
    from occplug.config import resolve_ref

    assert resolve_ref("occplug/trainer/debug").name == "debug.yaml"
