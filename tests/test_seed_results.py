"""Per-seed result files of the ablation scripts (``occplug.run.bench.write_seed_result`` / ``write_table_seeds``)."""

from __future__ import annotations

import importlib.metadata
import json
import math
import subprocess
from pathlib import Path

import torch

from occplug.run.bench import code_commit, write_seed_result, write_table_seeds

ROOT = Path(__file__).resolve().parents[1]


def test_one_seed_round_trips_with_nan_as_null(tmp_path):
    path = write_seed_result(tmp_path / "r", "base", 2, {"mIoU": 12.5, "IoU_car": math.nan}, {"epochs": 4})
    assert path == tmp_path / "r" / "base-seed2.json"
    record = json.loads(path.read_text())
    assert record["row"] == "base" and record["seed"] == 2
    assert record["values"] == {"mIoU": 12.5, "IoU_car": None}
    assert record["settings"] == {"epochs": 4}
    assert isinstance(record["command"], list) and record["command"]
    # where it was made: the same code and seed reproduce a number only on the same CPU kernel set
    assert record["environment"]["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert record["environment"]["packages"]["torch"] == importlib.metadata.version("torch")


def test_a_table_writes_one_file_per_row_and_seed_in_seed_order(tmp_path):
    table = {"a": {"mIoU": [1.0, 2.0, 3.0]}, "b": {"mIoU": [4.0, 5.0, 6.0], "IoU": [7.0, 8.0, 9.0]}}
    paths = write_table_seeds(tmp_path, table, [0, 5, 7], {})
    assert sorted(p.name for p in paths) == sorted(f"{r}-seed{s}.json" for r in "ab" for s in (0, 5, 7))
    assert json.loads((tmp_path / "b-seed5.json").read_text())["values"] == {"mIoU": 5.0, "IoU": 8.0}
    assert json.loads((tmp_path / "a-seed7.json").read_text())["values"] == {"mIoU": 3.0}


def test_the_commit_is_the_checkouts():
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    if head.returncode != 0:  # not a git checkout (an installed copy): nothing to compare with
        assert code_commit(ROOT) is None
        return
    commit = code_commit(ROOT)
    assert commit is not None and commit.removesuffix("-dirty") == head.stdout.strip()


def test_outside_git_there_is_no_commit(tmp_path):
    assert code_commit(tmp_path) is None


def test_a_script_records_the_commit_it_started_at(tmp_path):
    path = write_seed_result(tmp_path, "base", 0, {"mIoU": 1.0}, {}, commit="0123abc")
    assert json.loads(path.read_text())["commit"] == "0123abc"
