"""The markers pyproject.toml declares do what it says: ``slow`` tests are deselected unless ``-m slow``."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SAMPLE = """
import pytest

def test_quick():
    pass

@pytest.mark.slow
def test_long():
    pass

@pytest.mark.parametrize("n", [pytest.param(1, marks=pytest.mark.slow), 2])
def test_points(n):
    pass
"""


def _collected(folder: Path, *args: str) -> list[str]:
    """The test ids the project's configuration (its addopts) selects in ``folder`` with ``args`` added."""
    (folder / "test_sample.py").write_text(SAMPLE)
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-c", str(ROOT / "pyproject.toml"), "--rootdir", str(folder)]
        + ["-n", "0", "-p", "no:cacheprovider", "--collect-only", "-q", *args, str(folder)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    return sorted(line.split("::", 1)[1] for line in proc.stdout.splitlines() if "::" in line)


def test_slow_tests_are_deselected_unless_asked_for(tmp_path):
    assert _collected(tmp_path) == ["test_points[2]", "test_quick"]
    assert _collected(tmp_path, "-m", "slow") == ["test_long", "test_points[1]"]
    assert len(_collected(tmp_path, "-m", "slow or not slow")) == 4
