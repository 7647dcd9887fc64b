"""``trainer.precision=bf16-mixed`` trains the baseline on CPU; geometry, splat and metrics stay float32."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import torch

from occplug.run import runner
from occplug.testing import run_config

ROOT = Path(__file__).resolve().parents[1]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
TINY = ["data.preset=tiny", "trainer.accelerator=cpu"]


def test_one_step_bf16_mixed_fit_has_finite_loss_and_metrics(tmp_path: Path) -> None:
    run = tmp_path / "bf16"
    overrides = [*TINY, "trainer.precision=bf16-mixed", "trainer.max_steps=1", "trainer.log_every_n_steps=1"]
    results = run_config(BASELINE, run_dir=run, overrides=overrides)
    saved = json.loads((run / "metrics.json").read_text())
    assert saved["global_step"] == 1
    for key in ("mIoU", "IoU"):
        assert math.isfinite(saved[key]) and math.isfinite(results[key]), key
    assert saved["IoU"] > 0
    rows = list(csv.DictReader((run / "logs" / "version_0" / "metrics.csv").open()))
    train_loss = [float(r["train/loss"]) for r in rows if r.get("train/loss")]
    val_loss = [float(r["val/loss"]) for r in rows if r.get("val/loss")]
    assert train_loss and val_loss
    assert all(math.isfinite(v) and v > 0 for v in train_loss + val_loss)


def test_bf16_autocast_forward_keeps_the_volume_and_metrics_in_float32() -> None:
    cfg = runner.load_config([BASELINE], TINY)
    dm = runner.build_datamodule(cfg)
    model = runner.build_model(cfg, dm).eval()
    batch = next(iter(dm.val_dataloader()))  # the baseline's label grid, unlike make_tiny_batch's
    with torch.no_grad():
        reference = model(batch)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            outputs = model(batch)
            losses = model.losses(batch, outputs)
            pred = model.occupancy_from(outputs)
    assert outputs.image_features.dtype == torch.bfloat16  # the encoder really ran in bf16
    assert outputs.lifted.volume.dtype == torch.float32  # the splat pools in float32
    scale = reference.lifted.volume.abs().max()
    assert (outputs.lifted.volume - reference.lifted.volume).abs().max() < 0.05 * scale
    assert all(torch.isfinite(v) for v in losses.values())
    metric = model.val_metrics["occ3d_miou"]
    metric.update(pred, batch)
    values = metric.compute()
    metric.reset()
    assert metric.confmat.dtype == torch.int64
    assert all(v.dtype == torch.float32 for v in values.values())
    assert math.isfinite(float(values["IoU"]))


def test_a_bf16_recipe_on_a_machine_without_a_gpu_trains_at_32_true_with_one_notice(monkeypatch) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    notice = runner.cpu_precision_notice({"precision": "bf16-mixed"})
    assert notice is not None and notice.startswith("notice: trainer.precision=bf16-mixed") and "\n" not in notice
    assert runner.cpu_precision_notice({"precision": "bf16-mixed", "accelerator": "auto"}) == notice
    # the user's explicit choices are kept: a named CPU, full precision, bf16 weights without autocast
    assert runner.cpu_precision_notice({"precision": "bf16-mixed", "accelerator": "cpu"}) is None
    assert runner.cpu_precision_notice({"precision": "32-true"}) is None
    assert runner.cpu_precision_notice({"precision": "bf16-true"}) is None
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert runner.cpu_precision_notice({"precision": "bf16-mixed"}) is None


def test_fit_of_a_bf16_recipe_without_a_gpu_says_so_and_runs_in_float32(tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    run = tmp_path / "auto"
    overrides = ["data.preset=tiny", "trainer.precision=bf16-mixed", "trainer.accelerator=auto"]
    run_config(BASELINE, run_dir=run, overrides=overrides)  # the debug trainer's step limits, not its CPU
    err = capsys.readouterr().err
    assert sum(line.startswith("notice: trainer.precision=bf16-mixed") for line in err.splitlines()) == 1
    assert json.loads((run / "metrics.json").read_text())["global_step"] == 2
    trainer = runner._trainer({"trainer": {"precision": "bf16-mixed"}}, None, [])
    assert trainer.precision == "32-true"
