"""QueryOcc's tools, ``python -m occplug_queryocc.<name>`` (ablate, bench, window_coverage): each prints its help,
and importing one only defines things (its work runs in ``main()``)."""

from __future__ import annotations

import ast
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

MODULES = ["occplug_queryocc.ablate", "occplug_queryocc.bench", "occplug_queryocc.window_coverage"]

#: imported with argv that no tool accepts and argparse's parsing disabled: a tool that read its arguments (or
#: started its work) on import fails; what it printed or wrote into the working folder is checked after
IMPORT_ALL = """
import argparse, importlib, sys

def refuse(*args, **kwargs):
    raise AssertionError("argparse parsed arguments on import")

argparse.ArgumentParser.parse_args = argparse.ArgumentParser.parse_known_args = refuse
sys.argv = ["not-a-tool", "--not-an-option"]
for name in sys.stdin.read().split():
    assert callable(importlib.import_module(name).main), name
"""


def _run(args: list[str], cwd: Path, stdin: str | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONDONTWRITEBYTECODE": "1"}
    return subprocess.run(
        [sys.executable, *args], cwd=cwd, env=env, input=stdin, capture_output=True, text=True, timeout=300
    )


@pytest.mark.parametrize("module", MODULES)
def test_the_tool_runs_as_a_module_and_prints_its_help(module, tmp_path):
    proc = _run(["-m", module, "--help"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.startswith(f"usage: python -m {module} "), proc.stdout[:300]
    assert "scripts/" not in proc.stdout  # the help names the module, not the script it once was
    assert not any(tmp_path.iterdir())


def test_importing_the_tools_only_defines_things(tmp_path):
    proc = _run(["-c", IMPORT_ALL], tmp_path, stdin="\n".join(MODULES))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout == "" and "usage:" not in proc.stderr
    assert not any(tmp_path.iterdir()), sorted(p.name for p in tmp_path.iterdir())


@pytest.mark.parametrize("module", MODULES)
def test_the_tool_does_its_work_under_the_main_guard(module):
    """At module level: imports, definitions and constants; the work is in ``main()``, run under the guard."""
    tree = ast.parse(Path(importlib.util.find_spec(module).origin).read_text())
    guard = "if __name__ == '__main__':"
    for node in tree.body:
        if isinstance(node, ast.If):
            assert ast.unparse(node).startswith(guard), ast.unparse(node)[:200]
            continue
        docstring = isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)
        allowed = (ast.Import, ast.ImportFrom, ast.FunctionDef, ast.ClassDef, ast.Assign, ast.AnnAssign)
        assert docstring or isinstance(node, allowed), ast.unparse(node)[:200]
    assert [ast.unparse(n)[: len(guard)] for n in tree.body if isinstance(n, ast.If)] == [guard]
