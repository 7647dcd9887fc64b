"""The import boundary: the core knows no plugin, no plugin knows another, plugins and scripts use the plugin API.

The plugin API is the modules in ``occplug.PUBLIC_MODULES``, each by the names in its ``__all__`` (read from the
source, so a lazily loaded name counts). The rules, checked over the tree's source by its syntax alone:

1. nothing under ``occplug/`` imports a plugin (``occplug_*``);
2. a plugin (its package and its tests) imports no other plugin;
3. a plugin (package and tests) and a script under ``scripts/`` import from ``occplug`` only public modules,
   and only names in their ``__all__`` (or a public submodule: ``from occplug.run import runner``);
4. no ``_name`` is imported from a module of another package (the core's own tests, which test internals,
   and a plugin's tests of that plugin are exempt).
"""

from __future__ import annotations

import ast
import subprocess
import sys
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import occplug

ROOT = Path(__file__).resolve().parents[1]
PLUGIN_DIRS = {  # plugin package name -> the folders holding its package and its tests
    "occplug_queryocc": [ROOT / "plugins" / "occplug_queryocc"],
    "occplug_occle": [ROOT / "plugins" / "occplug_occle"],
    "occplug_duocc": [ROOT / "plugins" / "occplug_duocc"],
    "occplug_example": [ROOT / "plugins" / "example" / "src" / "occplug_example", ROOT / "plugins" / "example" / "tests"],
}


@dataclass(frozen=True)
class Import:
    """One imported name: ``from module import name`` (``name`` None for ``import module``)."""

    path: Path
    line: int
    module: str
    name: str | None

    def __str__(self) -> str:
        what = f"import {self.module}" if self.name is None else f"from {self.module} import {self.name}"
        return f"{self.path.relative_to(ROOT)}:{self.line}: {what}"


def module_name(path: Path) -> str | None:
    """The dotted name of a file inside a package (``None`` for a test or a script, which have none)."""
    parts: list[str] = []
    folder = path.parent
    while (folder / "__init__.py").is_file():
        parts.insert(0, folder.name)
        folder = folder.parent
    if not parts:
        return None
    return ".".join(parts if path.name == "__init__.py" else [*parts, path.stem])


def package_of(path: Path) -> str:
    """The package a file belongs to (its folder, for a file outside any package)."""
    name = module_name(path)
    if name is None:
        return str(path.parent)
    return name if path.name == "__init__.py" else name.rpartition(".")[0]


def imports(path: Path) -> list[Import]:
    """Every import of ``path``, relative ones resolved to absolute module names."""
    found: list[Import] = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found.extend(Import(path, node.lineno, alias.name, None) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:
                base = package_of(path).split(".")
                base = base[: len(base) - (node.level - 1)]
                module = ".".join([*base, module] if module else base)
            found.extend(Import(path, node.lineno, module, alias.name) for alias in node.names)
    return found


@cache
def public_names(module: str) -> frozenset[str]:
    """The names in ``module``'s ``__all__``, read from its source.

    A ``*_LAZY`` entry adds that dict's keys; a ``*submodule.__all__`` entry adds that submodule's names.
    """
    spec_path = ROOT / Path(*module.split("."))
    path = spec_path / "__init__.py" if spec_path.is_dir() else spec_path.with_suffix(".py")
    tree = ast.parse(path.read_text())
    dicts = {
        t.id: node.value
        for node in tree.body
        if isinstance(node, ast.Assign | ast.AnnAssign) and isinstance(node.value, ast.Dict)
        for t in (node.targets if isinstance(node, ast.Assign) else [node.target])
        if isinstance(t, ast.Name)
    }
    for node in tree.body:
        targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node, ast.AnnAssign) else []
        if any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets):
            names: set[str] = set()
            for element in node.value.elts:
                if isinstance(element, ast.Starred) and isinstance(element.value, ast.Attribute):
                    names.update(public_names(f"{module}.{element.value.value.id}"))
                elif isinstance(element, ast.Starred):
                    names.update(k.value for k in dicts[element.value.id].keys)
                else:
                    names.add(element.value)
            return frozenset(names)
    raise AssertionError(f"{path}: public module without __all__")


def sources(*folders: Path) -> list[Path]:
    return sorted(p for folder in folders for p in folder.rglob("*.py") if "__pycache__" not in p.parts)


def is_core(module: str) -> bool:
    return module == "occplug" or module.startswith("occplug.")


def plugin_of(module: str) -> str | None:
    top = module.split(".")[0]
    return top if top.startswith("occplug_") else None


def test_the_core_imports_no_plugin():
    bad = [str(i) for i in (i for p in sources(ROOT / "occplug") for i in imports(p)) if plugin_of(i.module)]
    assert not bad, "the core imports a plugin:\n" + "\n".join(bad)


def test_no_plugin_imports_another():
    bad = [
        str(i)
        for plugin, folders in PLUGIN_DIRS.items()
        for i in (i for p in sources(*folders) for i in imports(p))
        if plugin_of(i.module) not in (None, plugin)
    ]
    assert not bad, "a plugin imports another plugin:\n" + "\n".join(bad)


def api_violation(i: Import) -> str | None:
    """Why ``i`` breaks rule 3, or None."""
    if not is_core(i.module) or (i.name is not None and f"{i.module}.{i.name}" in occplug.PUBLIC_MODULES):
        return None  # not the core's, or a public module itself (`from occplug.run import runner`)
    if i.module not in occplug.PUBLIC_MODULES:
        return f"{i}  ({i.module} is not a public module)"
    if i.name is not None and i.name not in public_names(i.module):
        return f"{i}  ({i.name} is not in {i.module}.__all__)"
    return None


def test_plugins_and_scripts_use_only_the_plugin_api():
    folders = [f for fs in PLUGIN_DIRS.values() for f in fs] + [ROOT / "scripts"]
    bad = [v for p in sources(*folders) for i in imports(p) if (v := api_violation(i))]
    assert not bad, "imports outside the plugin API (occplug.PUBLIC_MODULES):\n" + "\n".join(bad)


def test_no_private_name_crosses_a_package():
    plugin_packages = [p for fs in PLUGIN_DIRS.values() for p in sources(*fs) if module_name(p) is not None]
    files = sources(ROOT / "occplug") + plugin_packages + sources(ROOT / "scripts")
    bad = []
    for path in files:
        for i in imports(path):
            private = i.name is not None and i.name.startswith("_") and not i.name.startswith("__")
            source_package = i.module if (ROOT / Path(*i.module.split("."))).is_dir() else i.module.rpartition(".")[0]
            if private and (is_core(i.module) or plugin_of(i.module)) and source_package != package_of(path):
                bad.append(str(i))
    assert not bad, "a private name imported from another package:\n" + "\n".join(bad)


def module_aliases(path: Path) -> dict[str, str]:
    """Local names bound to occplug or plugin *modules* by ``path``'s imports (``from occplug.run import runner``,
    ``import occplug.geometry as g``), mapped to the module's dotted name."""
    aliases = {}
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.asname and (is_core(alias.name) or plugin_of(alias.name)):
                    aliases[alias.asname] = alias.name
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:
                dotted = f"{node.module}.{alias.name}"
                target = ROOT / Path(*dotted.split("."))
                if (is_core(dotted) or plugin_of(dotted)) and (target.is_dir() or target.with_suffix(".py").is_file()):
                    aliases[alias.asname or alias.name] = dotted
    return aliases


def test_no_private_name_of_another_package_is_read_through_its_module():
    plugin_packages = [p for fs in PLUGIN_DIRS.values() for p in sources(*fs) if module_name(p) is not None]
    bad = []
    for path in sources(ROOT / "occplug") + plugin_packages + sources(ROOT / "scripts"):
        aliases = module_aliases(path)
        for node in ast.walk(ast.parse(path.read_text())):
            if (
                isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name)
                and node.value.id in aliases
                and node.attr.startswith("_")
                and not node.attr.startswith("__")
                and aliases[node.value.id].rpartition(".")[0] != package_of(path)
            ):
                bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: {aliases[node.value.id]}.{node.attr}")
    assert not bad, "a private name of another package read through its module:\n" + "\n".join(bad)


def test_every_public_module_exists_and_exports_what_it_lists():
    import importlib

    for name in occplug.PUBLIC_MODULES:
        module = importlib.import_module(name)
        missing = [n for n in public_names(name) if not hasattr(module, n)]
        assert not missing, f"{name}.__all__ lists names it does not have: {missing}"


def test_the_plugin_api_is_documented():
    text = (ROOT / "docs" / "plugins.md").read_text()
    undocumented = [m for m in occplug.PUBLIC_MODULES if f"`{m}`" not in text]
    assert not undocumented, f"docs/plugins.md does not name these public modules: {undocumented}"


def test_import_occplug_does_not_import_lightning():
    code = (
        "import sys, occplug, occplug.interfaces, occplug.geometry, occplug.data, occplug.constraints, occplug.nn, "
        "occplug.streams; "
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('lightning', 'pytorch_lightning', 'torchmetrics')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]", f"importing the facade and the contract modules imports {out}"
