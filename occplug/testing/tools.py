"""Checks for a plugin's command-line tools (modules run as ``python -m <package>.<tool>``).

A tool prints its help, does its work only in ``main()`` under the ``__main__`` guard, and importing it (from a
test, or by a tool of its own) only defines things: it reads no arguments, prints nothing and writes no file.
"""

from __future__ import annotations

import ast
import importlib.util
import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

__all__ = ["check_tool_help", "check_tool_main_guard", "check_tools_import_quietly"]

#: imported with argv that no tool accepts and argparse's parsing disabled: a tool that read its arguments (or
#: started its work) on import fails; what it printed or wrote into the working folder is checked after
_IMPORT_ALL = """
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


def check_tool_help(module: str, cwd: Path) -> None:
    """``python -m <module> --help`` exits 0, its usage names the module (not a script path), and it writes
    nothing into ``cwd`` (an empty folder)."""
    proc = _run(["-m", module, "--help"], cwd)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.startswith(f"usage: python -m {module} "), proc.stdout[:300]
    assert "scripts/" not in proc.stdout
    assert not any(Path(cwd).iterdir())


def check_tools_import_quietly(modules: Sequence[str], cwd: Path) -> None:
    """Importing every one of ``modules`` (in a fresh interpreter in the empty folder ``cwd``) parses no arguments,
    prints nothing and writes nothing, and each has a ``main``."""
    proc = _run(["-c", _IMPORT_ALL], cwd, stdin="\n".join(modules))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout == "" and "usage:" not in proc.stderr
    assert not any(Path(cwd).iterdir()), sorted(p.name for p in Path(cwd).iterdir())


def check_tool_main_guard(module: str) -> None:
    """At module level only imports, definitions and constants; the work runs under one ``__main__`` guard."""
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
