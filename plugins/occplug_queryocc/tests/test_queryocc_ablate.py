"""occplug_queryocc.tools.ablate re-scores a trained run (another split, evaluation-only overrides) without retraining."""

import json

from occplug.run import bench
from occplug_queryocc.tools import ablate

TINY = ["--seeds", "0", "--rows", "base", "--preset", "tiny", "--epochs", "1"]
SET = ["--set", "trainer.limit_train_batches=2", "trainer.limit_val_batches=2", "trainer.limit_test_batches=2"]


def test_a_rescored_run_equals_its_own_validation_and_is_cached(tmp_path, capsys, monkeypatch):
    out = tmp_path / "abl"
    ablate.main([*TINY, *SET, "--out", str(out)])
    run = out / "base-seed0"
    trained = json.loads((run / "metrics.json").read_text())
    assert "val split" in capsys.readouterr().out
    # the default voxel_samples, given as an evaluation-only override: validate re-scores the same checkpoint
    ablate.main([*TINY, *SET, "--out", str(out), "--eval-set", "model.heads.occupancy.voxel_samples=1"])
    (cached,) = run.glob("metrics_val_*.json")
    again = json.loads(cached.read_text())
    assert again["_eval_set"] == ["model.heads.occupancy.voxel_samples=1"]
    assert {k: again[k] for k in ablate.COLUMNS.values()} == {k: trained[k] for k in ablate.COLUMNS.values()}
    # the test split; a second pass reads the cache (nothing runs: a subprocess would fail here)
    ablate.main([*TINY, *SET, "--out", str(out), "--split", "test"])
    assert (run / "metrics_test.json").is_file() and "test split" in capsys.readouterr().out

    def no_process(*args, **kwargs):
        raise AssertionError("re-scored although cached")

    monkeypatch.setattr(bench.subprocess, "run", no_process)
    ablate.main([*TINY, *SET, "--out", str(out), "--split", "test"])


def test_the_calibrated_protocol_is_the_aligned_world_read_at_sub_voxels():
    from occplug.data.synthetic import preset
    from occplug.run.runner import load_config

    world, overrides = ablate.PROTOCOLS["calibrated"]
    cfg = load_config(["queryocc/base"], [f"data.preset={world}", *overrides])
    aligned = preset(world).grid
    assert tuple(cfg["grid"]["range"]) == tuple(aligned.lower) + tuple(aligned.upper)  # labels on its grid
    bev = cfg["model"]["view_transform"]["grid"]["range"]
    assert (bev[2], bev[5]) == (aligned.lower[2], aligned.upper[2])  # the BEV pools the scored heights
    assert cfg["model"]["heads"]["occupancy"]["voxel_samples"] == 3
    assert ablate.PROTOCOLS["default"] == ("default", [])  # the default protocol changes nothing
