"""fit's checks before anything is written: models that train nothing, Lightning's own
misconfiguration and a component's error on the first batch -- exit 2, one line, no run directory;
and the first-batch check changes nothing about the run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from occplug.cli import main
from occplug.run import runner

ROOT = Path(__file__).resolve().parents[2]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
TINY = ["data.preset=tiny", "trainer.enable_progress_bar=false", "trainer.max_steps=2", "trainer.limit_val_batches=1"]


def fit_fails(tmp_path, capsys, *overrides: str) -> str:
    run_dir = tmp_path / "run"
    code = main(["fit", "-c", BASELINE, *TINY, *overrides, "--run-dir", str(run_dir)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert not run_dir.exists(), "a failed check must leave no run directory"
    errors = [line for line in err if line.startswith("error: ")]
    assert len(errors) == 1 and "Traceback" not in "\n".join(err)
    return errors[0]


@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        (["~model.supervision.voxel_labels"], "error: model.supervision: the model has no supervision source"),
        (
            ["model.supervision.voxel_labels.weight=0.0"],
            "error: model.supervision: every loss weight is <= 0 (voxel_labels: 0)",
        ),
        (["~model.heads.occupancy"], "error: model.heads.occupancy: the model evaluates through an occupancy head"),
    ],
)
def test_fit_refuses_models_that_train_nothing(tmp_path, capsys, overrides, expected):
    assert fit_fails(tmp_path, capsys, *overrides).startswith(expected)


def test_validate_accepts_a_model_without_supervision(tmp_path, capsys):
    run = tmp_path / "ok"
    assert main(["fit", "-c", BASELINE, *TINY, "--run-dir", str(run)]) == 0
    ckpt = run / "checkpoints" / "last.ckpt"
    assert main(["validate", "--ckpt", str(ckpt), "~model.supervision.voxel_labels"]) == 0


def test_lightning_misconfiguration_is_one_line_naming_the_trainer_key(tmp_path, capsys):
    line = fit_fails(tmp_path, capsys, "trainer.accelerator=mps")  # no Linux machine has Apple's MPS (a GPU one may have CUDA)
    assert line.startswith("error: trainer.accelerator = 'mps': ")


def test_a_first_batch_error_is_one_line_before_anything_is_written(tmp_path, capsys):
    # the tiny preset's images are 32 x 64 pixels: a stride-16 encoder with 3 levels needs multiples of 64
    line = fit_fails(tmp_path, capsys, "model.encoder.stride=16", "model.encoder.levels=3")
    assert "is not divisible by the encoder stride 64" in line


def test_the_first_batch_check_changes_nothing(tmp_path, monkeypatch):
    """Same weights (BatchNorm buffers included) and metrics with and without the check."""
    cfg = runner.load_config([BASELINE, "occplug/trainer/debug"], [*TINY, "trainer.max_steps=4"])
    runner.fit(cfg, tmp_path / "checked")
    monkeypatch.setattr(runner, "first_batch_check", lambda model, dm: None)
    runner.fit(cfg, tmp_path / "unchecked")
    a = json.loads((tmp_path / "checked" / "metrics.json").read_text())
    b = json.loads((tmp_path / "unchecked" / "metrics.json").read_text())
    assert a == b
    sa = torch.load(tmp_path / "checked" / "checkpoints" / "last.ckpt", weights_only=True)["state_dict"]
    sb = torch.load(tmp_path / "unchecked" / "checkpoints" / "last.ckpt", weights_only=True)["state_dict"]
    assert sa.keys() == sb.keys() and any("running_mean" in k for k in sa)
    for key in sa:
        assert torch.equal(sa[key], sb[key]), key


def test_a_tiny_run_logs_each_epoch_without_the_logging_interval_warning(tmp_path):
    import warnings

    cfg = runner.load_config(
        [BASELINE, "occplug/trainer/debug"], [*TINY, "trainer.max_steps=3", "trainer.log_every_n_steps=50"]
    )
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        runner.fit(cfg, tmp_path / "run")
    assert not [w for w in seen if "logging interval" in str(w.message)]
    csv = next((tmp_path / "run" / "logs").glob("version_*/metrics.csv")).read_text()
    assert "train/loss" in csv.splitlines()[0]  # logged although the epoch has fewer steps than 50
