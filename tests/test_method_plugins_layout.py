"""The three method plugins share one layout and one naming policy, so a reader who knows one knows all three:
``plugin.py``; the component modules by kind (a kind may be a sub-package); ``blocks/``; ``tools/`` (run as
``python -m occplug_<m>.tools.<name>``); ``configs/``; ``tests/``; a README of user documentation. Results live in
``results/<method>/`` at the root, investigations in ``investigations/<method>/``: neither is installed."""

from __future__ import annotations

import ast
import re
import shutil
import subprocess
import sys
import zipfile
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
#: what a method package holds at its top level: the same names in all three
TOP_LEVEL = (
    {"__init__.py", "plugin.py", "README.md", "configs", "tests", "docs", "blocks", "tools"}
    | {f"{m}.py" for m in KIND_MODULES.values()}
    | set(KIND_MODULES.values())
)
#: the README's sections, in this order (a heading starting with each)
README_SECTIONS = ("## What it is", "## Components", "## Commands", "## Differences from the paper", "## Claims")
#: the sub-sections of "## Commands", in this order
COMMAND_SECTIONS = ("### Synthetic world", "### Real data", "### Ablation")
#: a screen is about 50 lines: the complete real-data command starts on the first two
TWO_SCREENS = 100


def package(method: str) -> Path:
    return ROOT / "plugins" / f"occplug_{method}"


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
        home = f"occplug_{method}.{module}"
        for entry in registry.entries(kind):
            where = entry.source.partition(":")[0]
            if entry.plugin == method and where != home and not where.startswith(home + "."):
                misplaced.append(f"{entry.name} in {where}")
    assert not misplaced, f"{method}: components outside occplug_{method}.<kind module>: {misplaced}"


@pytest.mark.parametrize("method", METHODS)
def test_each_plugin_has_the_one_layout(method):
    folder = package(method)
    for name in ("__init__.py", "plugin.py", "README.md", "configs", "tests", "tools/__init__.py"):
        assert (folder / name).exists(), f"plugins/occplug_{method}/{name} is missing"
    for tool in ("ablate", "bench"):
        assert (folder / "tools" / f"{tool}.py").is_file(), f"plugins/occplug_{method}/tools/{tool}.py is missing"
    names = {p.name for p in folder.iterdir() if p.name != "__pycache__"}
    assert names <= TOP_LEVEL, f"plugins/occplug_{method} holds {sorted(names - TOP_LEVEL)} outside the one layout"
    # the results are not in the package: RESULTS.md and its per-seed JSON are under results/<method>/
    assert not list(folder.rglob("RESULTS.md")) and not list(folder.rglob("*.json"))
    assert (ROOT / "results" / method / "RESULTS.md").is_file()


def _modules(method: str) -> dict[str, Path]:
    """The installed package's modules (``occplug_<m>.x.y`` -> file), tests and configs left out."""
    folder = package(method)
    found = {}
    for path in folder.rglob("*.py"):
        parts = path.relative_to(folder).with_suffix("").parts
        if parts[0] == "tests" or "__pycache__" in parts:
            continue
        name = ".".join((f"occplug_{method}", *parts)).removesuffix(".__init__")
        found[name] = path
    return found


def _imported(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package's modules ``path`` imports (any nesting: the function-level imports of ``plugin.py`` count),
    each with the packages above it (importing ``a.b.c`` runs ``a/__init__`` and ``a/b/__init__``)."""
    here = name if path.name == "__init__.py" else name.rpartition(".")[0]
    targets = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = here.split(".")[: len(here.split(".")) - node.level + 1] if node.level else []
            module = ".".join([*base, *([node.module] if node.module else [])])
            targets |= {module, *(f"{module}.{a.name}" for a in node.names)}
        elif isinstance(node, ast.Import):
            targets |= {a.name for a in node.names}
    out = set()
    for target in targets:
        parts = target.split(".")
        out |= {".".join(parts[:k]) for k in range(1, len(parts) + 1)} & modules.keys()
    return out


@pytest.mark.parametrize("method", METHODS)
def test_plugin_py_reaches_every_installed_module_but_the_tools(method):
    modules = _modules(method)
    start = f"occplug_{method}.plugin"
    reached, todo = set(), [f"occplug_{method}", start]
    while todo:
        name = todo.pop()
        if name not in reached:
            reached.add(name)
            todo.extend(_imported(name, modules[name], modules))
    tools = f"occplug_{method}.tools"
    unreached = sorted(m for m in modules.keys() - reached if m != tools and not m.startswith(tools + "."))
    assert not unreached, (
        f"{start} does not reach {unreached}: a tool goes to tools/, an investigation out of the package"
    )
    assert not any(m.startswith(tools) for m in reached), f"{start} imports a tool"


def test_a_reachability_failure_is_reported(tmp_path, monkeypatch):
    """The reachability walk sees a module nothing imports (the test above can fail)."""
    folder = tmp_path / "plugins" / "occplug_fake"
    (folder / "tools").mkdir(parents=True)
    (folder / "__init__.py").write_text("")
    (folder / "plugin.py").write_text("def hook():\n    from .used import x\n")
    (folder / "used.py").write_text("x = 1\n")
    (folder / "orphan.py").write_text("y = 2\n")
    (folder / "tools" / "__init__.py").write_text("")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    with pytest.raises(AssertionError, match=r"occplug_fake\.orphan"):
        test_plugin_py_reaches_every_installed_module_but_the_tools("fake")


def test_investigations_are_outside_the_packages_and_each_is_documented():
    folder = ROOT / "investigations"
    scripts = sorted(folder.glob("*/*.py"))
    assert scripts, "investigations/ holds no script"
    assert {p.parent.name for p in scripts} <= set(METHODS)
    readme = (folder / "README.md").read_text()
    undocumented = [p.relative_to(folder).as_posix() for p in scripts if p.relative_to(folder).as_posix() not in readme]
    assert not undocumented, f"investigations/README.md does not say what these answered: {undocumented}"


def _defined(path: Path) -> set[str]:
    """The names a module defines at its top level (functions, classes, assignments, imports)."""
    names = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names |= {n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)}
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names |= {(a.asname or a.name).split(".")[0] for a in node.names}
    return names


def _module_file(module: str) -> Path | None:
    """The source of ``occplug...`` / ``occplug_<m>...`` in this checkout (a package's ``__init__.py``)."""
    base = ROOT / "plugins" if module.startswith("occplug_") else ROOT
    path = base.joinpath(*module.split("."))
    for candidate in (path.with_suffix(".py"), path / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


@pytest.mark.parametrize(
    "script", sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "investigations").glob("*/*.py"))
)
def test_an_investigation_imports_what_exists(script):
    """What an investigation imports from occplug and the method packages exists (read from the source: importing
    one costs a Lightning import), so a move in a package that breaks it fails here; it prints its usage as
    ``python investigations/...``."""
    tree = ast.parse((ROOT / script).read_text())
    broken = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0].startswith("occplug"):
            source = _module_file(node.module)
            if source is None:
                broken.append(node.module)
                continue
            if node.module.startswith("occplug_"):  # a method package's names (the core's facades re-export lazily)
                inside = {p.stem for p in source.parent.iterdir()} if source.name == "__init__.py" else set()
                broken += [f"{node.module}.{a.name}" for a in node.names if a.name not in _defined(source) | inside]
    assert not broken, f"{script} imports what does not exist: {broken}"
    assert f'prog="python {script}"' in (ROOT / script).read_text()


def _sections(lines: list[str], prefix: str) -> list[tuple[int, str]]:
    return [(i, line) for i, line in enumerate(lines) if line.startswith(prefix + " ")]


@pytest.mark.parametrize("method", METHODS)
def test_the_readme_is_user_documentation_in_one_structure(method):
    path = package(method) / "README.md"
    lines = path.read_text().splitlines()
    assert lines[0].startswith("# "), f"{path.name}: no title"
    headings = [line for _, line in _sections(lines, "##")]
    at = [next((k for k, h in enumerate(headings) if h.startswith(s)), None) for s in README_SECTIONS]
    assert None not in at and at == sorted(at), (
        f"{method} README sections {headings}, expected in order {README_SECTIONS}"
    )
    body = {s: _body(lines, s) for s in README_SECTIONS}
    assert "```" in body["## What it is"], f"{method} README: 'What it is' has no component diagram"
    assert any(line.startswith("|") for line in body["## Components"]), f"{method} README: no components table"
    sub = [line for line in body["## Commands"] if line.startswith("### ")]
    where = [next((k for k, h in enumerate(sub) if h.startswith(s)), None) for s in COMMAND_SECTIONS]
    assert None not in where and where == sorted(where), f"{method} README commands {sub}, expected {COMMAND_SECTIONS}"
    claims = [line for line in body["## Claims"] if line.startswith("|")]
    assert len(claims) >= 3, f"{method} README: the claims table has no rows"
    assert f"../../results/{method}/RESULTS.md" in "\n".join(body["## Claims"]), "the claims table links the results"


def _body(lines: list[str], heading: str) -> list[str]:
    start = next(i for i, line in enumerate(lines) if line.startswith(heading))
    end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("## ")), len(lines))
    return lines[start + 1 : end]


@pytest.mark.parametrize("method", METHODS)
def test_the_complete_real_data_command_is_on_the_first_two_screens(method):
    lines = (package(method) / "README.md").read_text().splitlines()
    real = next(i for i, line in enumerate(lines) if line.startswith("### Real data"))
    fence = [i for i in range(real, len(lines)) if lines[i].startswith("```")][:2]
    block = lines[fence[0] + 1 : fence[1]]
    assert fence[0] < TWO_SCREENS, f"{method} README: the real-data commands start at line {fence[0] + 1}"
    fits = [line for line in block if re.match(r"occplug fit -c \w+/", line.strip())]
    assert fits, f"{method} README: the real-data block trains nothing"
    assert any(line.strip().startswith("occplug data") for line in block), "the data preparation is in the block"


def test_no_source_comment_cites_a_file_outside_the_repository():
    tracked = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True).stdout.split()
    if not tracked:  # not a git checkout
        pytest.skip("needs the git checkout")
    names = {Path(p).name for p in tracked}
    missing = []
    for folder in ("occplug", "plugins", "scripts", "configs"):
        for path in sorted((ROOT / folder).rglob("*")):
            if path.suffix in (".py", ".yaml") and "__pycache__" not in path.parts:
                for cited in re.findall(r"[\w./-]*[\w-]+\.md\b", path.read_text()):
                    if Path(cited).name not in names:
                        missing.append(f"{path.relative_to(ROOT)}: {cited}")
    assert not missing, f"comments cite files not in the repository: {missing}"


def test_a_wheel_holds_no_results(tmp_path):
    source = tmp_path / "src"
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info", "runs", "build")
    for name in ("occplug", "plugins"):
        shutil.copytree(ROOT / name, source / name, ignore=ignore)
    for method in METHODS:  # a result left inside a package would be what the wheel must not carry
        assert not list((source / "plugins" / f"occplug_{method}").rglob("*.json"))
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path / "w")]
    proc = subprocess.run([*cmd, str(source)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (wheel,) = (tmp_path / "w").glob("occplug-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert any(n.startswith("occplug_duocc/tools/") for n in names) and any(
        n.endswith("duocc/configs/full.yaml") for n in names
    )
    carried = [n for n in names if n.endswith((".json", "RESULTS.md")) or "/results/" in n or "/tests/" in n]
    assert not carried, f"the wheel carries results or tests: {carried}"
    assert not any(n.startswith("investigations/") for n in names)
