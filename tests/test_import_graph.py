"""The core has no import circle, and its imports point one way: down the layers.

No circle: no chain of imports among ``occplug``'s modules leads back to where it started. One way: every module
sits in one of :data:`LAYERS` and imports only from its own layer or those below it (an import that runs up the
layers is how a circle starts, even before it closes).

Every import statement counts, also one deferred into a function (a deferred import hides a circle from the
interpreter, not from the design); only imports under ``if TYPE_CHECKING:`` are left out. Importing
``a.b.c`` also runs ``a`` and ``a.b``, so a module depends on the packages above what it imports (but not on
its own parents, which Python runs before it anyway).
"""

from __future__ import annotations

import ast
from pathlib import Path

import occplug


def import_graph(root: Path) -> dict[str, set[str]]:
    """``{module: modules it imports}`` over the package at ``root`` (a folder with ``__init__.py``)."""
    files: dict[str, tuple[Path, bool]] = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        files[".".join(parts[:-1] if is_package else parts)] = (path, is_package)

    def known(name: str) -> str | None:  # the longest module prefix of a dotted name
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for module, (path, is_package) in files.items():
        targets: set[str] = set()
        for node in _imports(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets.update(alias.name for alias in node.names)
                continue
            source = _source(node, module, is_package)
            targets.add(source)
            targets.update(f"{source}.{alias.name}" for alias in node.names)  # `from pkg import submodule`
        deps: set[str] = set()
        for target in filter(None, map(known, targets)):
            parts = target.split(".")
            for i in range(1, len(parts) + 1):
                dep = ".".join(parts[:i])
                if dep in files and dep != module and not module.startswith(dep + "."):
                    deps.add(dep)
        graph[module] = deps
    return graph


def _source(node: ast.ImportFrom, module: str, is_package: bool) -> str:
    """The absolute module a ``from ... import`` in ``module`` reads from (relative levels resolved)."""
    if not node.level:
        return node.module or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[: len(base) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def _imports(tree: ast.AST) -> list[ast.Import | ast.ImportFrom]:
    """Every import statement of ``tree``, those under ``if TYPE_CHECKING:`` left out."""
    skipped: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skipped.update(id(inner) for stmt in node.body for inner in ast.walk(stmt))
    return [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom)) and id(n) not in skipped]


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle as ``[a, b, ..., a]``, or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for dep in sorted(graph.get(node, ())):
            if state.get(dep) == 1:
                return path[path.index(dep):] + [dep]
            if dep not in state and (found := visit(dep)):
                return found
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


#: The core's layers, lowest first: (name, module prefixes). A module belongs to the layer of its longest
#: matching prefix. ``occplug`` itself is the facade, above everything: a core module that imports it (rather
#: than a submodule through it) runs up to the top.
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    (
        "leaves",
        (
            "occplug.errors", "occplug.constraints", "occplug.slots", "occplug.settings", "occplug.hookspecs",
            "occplug.queries", "occplug.geometry", "occplug.nn", "occplug.ops", "occplug.streams", "occplug.context",
            "occplug.optim",
        ),
    ),
    ("data and metrics", ("occplug.data", "occplug.metrics", "occplug.ceilings")),
    ("interfaces and registry", ("occplug.interfaces", "occplug.kinds", "occplug.registry")),
    ("components and model", ("occplug.components", "occplug.model")),
    ("plugin manager", ("occplug.plugins",)),
    ("config", ("occplug.config",)),
    ("runs", ("occplug.run", "occplug.export", "occplug.viz", "occplug.testing", "occplug.builtin")),
    ("command line", ("occplug.cli",)),
    ("facade", ("occplug", "occplug.docs")),
)  # fmt: skip


def layer_of(module: str, layers: tuple[tuple[str, tuple[str, ...]], ...] = LAYERS) -> int:
    """Index in ``layers`` of the layer whose longest prefix matches ``module``."""
    best: tuple[int, int] | None = None
    for index, (_, prefixes) in enumerate(layers):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and (best is None or len(prefix) > best[1]):
                best = (index, len(prefix))
    if best is None:
        raise AssertionError(f"module {module} is in no layer; add it to LAYERS")
    return best[0]


def upward_imports(root: Path, layers: tuple[tuple[str, tuple[str, ...]], ...] = LAYERS) -> list[str]:
    """``"module:line -> target (layer -> layer)"`` for every import of the package at ``root`` whose target sits
    in a higher layer than the importing module (deferred imports count; ``TYPE_CHECKING`` ones do not)."""
    files: dict[str, bool] = {}
    paths: dict[str, Path] = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        name = ".".join(parts[:-1] if is_package else parts)
        files[name], paths[name] = is_package, path
    top = root.name
    found: list[str] = []
    for module, is_package in files.items():
        for node in _imports(ast.parse(paths[module].read_text())):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            else:
                source = _source(node, module, is_package)
                # `from pkg import submodule` imports the submodule; `from pkg import name` the package itself
                targets = [f"{source}.{a.name}" if f"{source}.{a.name}" in files else source for a in node.names]
            for target in targets:
                if target != top and not target.startswith(top + "."):
                    continue
                while target not in files:
                    target = target.rpartition(".")[0]
                if target != top and module.startswith(target + "."):
                    continue  # a module's own packages run before it anyway
                if module == target:
                    continue
                low, high = layer_of(module, layers), layer_of(target, layers)
                line = f"{module}:{node.lineno} -> {target} ({layers[low][0]} -> {layers[high][0]})"
                if high > low and line not in found:  # one line per import statement and target
                    found.append(line)
    return found


def _write(root: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    return root / "pkg"


def test_a_deferred_import_closing_a_circle_is_found(tmp_path):
    pkg = _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/a.py": "from .b import g\n",
        "pkg/b.py": "def g():\n    from pkg import a\n",
        "pkg/sub/__init__.py": "from . import c\n",
        "pkg/sub/c.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.sub import d\n",
        "pkg/sub/d.py": "from ..a import x\n",
    })
    graph = import_graph(pkg)
    assert graph == {"pkg": set(), "pkg.a": {"pkg.b"}, "pkg.b": {"pkg.a"}, "pkg.sub": {"pkg.sub.c"},
                     "pkg.sub.c": set(), "pkg.sub.d": {"pkg.a"}}
    assert find_cycle(graph) == ["pkg.a", "pkg.b", "pkg.a"]


def test_importing_a_submodule_depends_on_the_packages_above_it(tmp_path):
    pkg = _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/x.py": "import pkg.sub.y\n",
        "pkg/sub/__init__.py": "from ..x import f\n",  # pkg.sub runs pkg.x, which runs pkg.sub: a circle
        "pkg/sub/y.py": "",
    })
    graph = import_graph(pkg)
    assert graph["pkg.x"] == {"pkg.sub", "pkg.sub.y"}
    assert find_cycle(graph) == ["pkg.sub", "pkg.x", "pkg.sub"]


def test_an_import_up_the_layers_is_found_also_deferred_and_through_the_facade(tmp_path):
    pkg = _write(tmp_path, {
        "pkg/__init__.py": "from .low import f\n",
        "pkg/low.py": "def f():\n    from pkg.high import g\n    import pkg\n",
        "pkg/high.py": "from typing import TYPE_CHECKING\nfrom pkg import low\nif TYPE_CHECKING:\n    import pkg\n",
    })
    layers = (("low", ("pkg.low",)), ("high", ("pkg.high",)), ("facade", ("pkg",)))
    assert upward_imports(pkg, layers) == [
        "pkg.low:2 -> pkg.high (low -> high)",
        "pkg.low:3 -> pkg (low -> facade)",
    ]


def test_the_core_imports_point_down_the_layers():
    found = upward_imports(Path(occplug.__file__).parent)
    assert not found, f"{len(found)} imports run up the layers:\n" + "\n".join(found)


def test_the_core_has_no_import_circle():
    graph = import_graph(Path(occplug.__file__).parent)
    assert len(graph) > 50 and "occplug.data.nuscenes.reader" in graph["occplug.builtin"]
    cycle = find_cycle(graph)
    assert cycle is None, "import circle: " + " -> ".join(cycle)
