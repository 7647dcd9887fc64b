"""scripts/real_size.py's measuring worker and table, on the tiny synthetic world (the real-size run is the script's)."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_the_worker_times_one_step_and_one_validation_batch_and_profiles_the_step(script):
    real_size = script("real_size")
    job = {
        "refs": [str(ROOT / "configs" / "baseline.yaml")],
        "overrides": ["data.preset=tiny", "data.batch_size=2"],
        "device": "cpu",
        "batch": 1,
        "depth": 1,
    }
    rows = real_size.worker(job)
    assert len(rows) == 1
    row = rows[0]
    assert row["batch"] == 1 and row["recipe_batch"] == 2 and row["precision"] == "32-true"
    assert row["step_s"] > 0 and row["val_s"] > 0 and row["peak_bytes"] > 2**20
    assert row["voxels"] == 60 * 60 * 8  # the baseline's label grid
    assert row["params"] > 0
    # the saved activations are charged to the model's top-level parts and add up to the total
    assert set(row["saved_by_module"]) <= {
        "encoder",
        "view_transform",
        "scene",
        "heads",
        "supervision",
        "(outside any module)",
    }
    assert sum(row["saved_by_module"].values()) == row["saved_bytes"] > 0
    assert row["gpu_estimate_bytes"] == row["saved_bytes"] * 2 + 16 * row["params"]
    line = real_size.table([{"recipe": "baseline", **row}], "cpu").splitlines()[-1]
    assert line.startswith("| baseline | - | cpu | 32-true | 1 |") and line.endswith("|  |")


def test_a_failing_recipe_is_a_row_with_its_error(script, tmp_path):
    real_size = script("real_size")

    class Args:
        device, batch, depth, timeout, out = "cpu", 1, 1, 120, str(tmp_path)

    rows = real_size.run_recipe("bad", [str(ROOT / "configs" / "baseline.yaml")], ["data.preset=nowhere"], Args())
    assert len(rows) == 1 and "nowhere" in rows[0]["error"] and "step_s" not in rows[0]
