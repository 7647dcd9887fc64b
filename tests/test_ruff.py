"""``ruff check`` passes on the whole tree with the configuration in ``pyproject.toml`` (ruff is in the dev extra)."""

from __future__ import annotations

import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _ruff(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    try:
        from ruff.__main__ import find_ruff_bin
    except ImportError as exc:  # a dev dependency: its absence is a broken environment, not a reason to skip
        raise AssertionError("ruff is not installed: pip install -e '.[dev]'") from exc
    return subprocess.run([find_ruff_bin(), *args], cwd=cwd, capture_output=True, text=True, timeout=300)


def test_the_project_configuration_is_the_one_ruff_reads(tmp_path):
    """A line of 141 characters fails and one of 140 passes: the project's E501 limit is in force (the
    formatter wraps code at 120; only lines it cannot wrap may run to 140)."""
    config = ROOT / "pyproject.toml"
    (tmp_path / "ok.py").write_text(f'X = "{"a" * 134}"\n')
    (tmp_path / "long.py").write_text(f'X = "{"a" * 135}"\n')
    (tmp_path / "unsorted.py").write_text("import sys\nimport os\n\nprint(os, sys)\n")
    assert _ruff("check", "--config", str(config), "ok.py", cwd=tmp_path).returncode == 0
    long = _ruff("check", "--config", str(config), "--output-format", "concise", "long.py", cwd=tmp_path)
    assert long.returncode == 1 and "E501" in long.stdout
    unsorted = _ruff("check", "--config", str(config), "--output-format", "concise", "unsorted.py", cwd=tmp_path)
    assert unsorted.returncode == 1 and "I001" in unsorted.stdout


def test_ruff_check_passes_on_the_tree():
    result = _ruff("check", "--output-format", "concise", ".")
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-1000:]
