"""The three method plugins share one layout and one naming policy, so a reader who knows one knows all three."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("queryocc", "occle", "duocc")
#: where a component of each kind lives in a method plugin (a plugin registers only the kinds it has)
KIND_MODULES = {
    "view_transform": "view_transform",
    "point_encoder": "point_encoder",
    "scene": "scene",
    "head": "heads",
    "supervision": "supervision",
}


@pytest.mark.parametrize("method", METHODS)
def test_registry_names_carry_the_plugins_prefix(isolated_registry, method):
    registry = isolated_registry(entry_points=[method])
    names = [(e.kind, e.name) for e in registry.entries() if e.plugin == method]
    assert names, f"{method} registers nothing"
    unprefixed = [n for n in names if not n[1].startswith(f"{method}_")]
    assert not unprefixed, f"{method} registers names without its prefix '{method}_': {unprefixed}"


@pytest.mark.parametrize("method", METHODS)
def test_components_live_in_the_module_of_their_kind(isolated_registry, method):
    registry = isolated_registry(entry_points=[method])
    misplaced = []
    for kind, module in KIND_MODULES.items():
        for entry in registry.entries(kind):
            where = entry.source.partition(":")[0]
            # the mask decoder is one supervision source with a decoder of its own: its module says so
            if entry.plugin == method and where != f"occplug_{method}.{module}" and entry.name != "duocc_mask":
                misplaced.append(f"{entry.name} in {where}")
    assert not misplaced, f"{method}: components outside occplug_{method}.<kind module>: {misplaced}"


@pytest.mark.parametrize("method", METHODS)
def test_each_plugin_holds_its_docs_configs_and_scripts(method):
    folder = ROOT / "plugins" / f"occplug_{method}"
    for name in ("__init__.py", "plugin.py", "README.md", "RESULTS.md", "ablate.py", "bench.py", "configs", "tests"):
        assert (folder / name).exists(), f"plugins/occplug_{method}/{name} is missing"
    readme = (folder / "README.md").read_text().splitlines()
    assert len(readme) <= 300, f"plugins/occplug_{method}/README.md is {len(readme)} lines (user docs: at most 300)"
