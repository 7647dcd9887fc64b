"""``trainer.loggers``: names checked at config time, Lightning's loggers under the run directory, no adverts."""

from __future__ import annotations

import csv
import importlib.util
import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

from occplug.config import ConfigError
from occplug.run import runner
from occplug.run.loggers import build_loggers, check_logger_names, quiet_lightning_tips
from occplug.testing import run_config

ROOT = Path(__file__).resolve().parents[1]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
DEBUG = "occplug/trainer/debug"


def _has(package: str) -> bool:
    return importlib.util.find_spec(package) is not None


def test_logger_names_are_checked_with_a_suggestion():
    assert check_logger_names(["csv", "tensorboard", "csv"]) == ["csv", "tensorboard"]
    with pytest.raises(ConfigError) as err:
        runner.load_config([BASELINE, DEBUG], ["trainer.loggers=[csv,tensorbord]"])
    assert str(err.value) == (
        "trainer.loggers.1: unknown logger 'tensorbord'; did you mean 'tensorboard'? "
        "(one of: csv, tensorboard, mlflow, wandb)"
    )
    with pytest.raises(ConfigError, match=r"^trainer.loggers: expected a list of logger names"):
        runner.load_config([BASELINE], ["trainer.loggers=tensorboard"])
    cfg = runner.load_config([BASELINE], ["trainer.loggers=[tensorboard]"])  # a valid list passes validation
    assert cfg["trainer"]["loggers"] == ["tensorboard"]


def test_csv_is_always_first_and_on(tmp_path):
    from lightning.pytorch.loggers import CSVLogger

    for names in (None, [], ["csv"]):
        built = build_loggers(names, tmp_path)
        assert len(built) == 1 and isinstance(built[0], CSVLogger)
        assert Path(built[0].log_dir) == tmp_path / "logs" / "version_0"


def test_a_missing_package_is_one_line_naming_it_and_nothing_is_written(tmp_path, monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "wandb" else real(name, *a))
    with pytest.raises(ConfigError) as err:
        build_loggers(["csv", "wandb"], tmp_path)
    assert (
        str(err.value) == "trainer.loggers: 'wandb' needs the wandb package, which is not installed: pip install wandb"
    )
    cfg = runner.load_config([BASELINE, DEBUG], ["trainer.loggers=[wandb]"])
    with pytest.raises(runner.RunError, match="pip install wandb"):
        runner.fit(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_the_lightning_tip_is_filtered_and_other_messages_pass():
    from lightning.pytorch.utilities.rank_zero import rank_zero_info

    quiet_lightning_tips()
    quiet_lightning_tips()  # idempotent
    seen: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            seen.append(record.getMessage())

    log = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    handler, level = Keep(), log.level
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    try:
        rank_zero_info(
            "💡 Tip: For seamless cloud logging, try installing [litlogger](https://pypi.org/project/litlogger/)"
        )
        rank_zero_info("GPU available: False, used: False")
    finally:
        log.removeHandler(handler)
        log.setLevel(level)
    assert seen == ["GPU available: False, used: False"]


@pytest.mark.skipif(not _has("tensorboard"), reason="tensorboard not installed (pip install 'occplug[tensorboard]')")
def test_fit_with_csv_and_tensorboard_writes_both_and_prints_no_advert(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "occplug.cli", "fit", "-c", BASELINE, "-c", "occplug/trainer/debug", "--run-dir", str(run),
         "trainer.log_every_n_steps=1", "trainer.loggers=[csv,tensorboard]",
         "callbacks.bev={type: bev_panel_logger, samples: [0]}"],
        cwd=ROOT, capture_output=True, text=True, env={**os.environ}, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "litlogger" not in proc.stderr and "💡" not in proc.stderr + proc.stdout
    assert list((run / "tensorboard" / "version_0").glob("events.out.tfevents.*"))
    acc = EventAccumulator(str(run / "tensorboard" / "version_0"), size_guidance={"images": 0, "scalars": 0})
    acc.Reload()
    # the same numbers reach both loggers: TensorBoard's train/loss equals metrics.csv's, step by step
    with open(run / "logs" / "version_0" / "metrics.csv") as f:
        rows = [r for r in csv.DictReader(f) if r.get("train/loss")]
    tb = {e.step: e.value for e in acc.Scalars("train/loss")}
    assert len(rows) == 2 and sorted(tb) == sorted(int(r["step"]) for r in rows)
    for r in rows:
        assert tb[int(r["step"])] == pytest.approx(float(r["train/loss"]), rel=1e-6)
    assert "val/mIoU" in acc.Tags()["scalars"]
    # the viz callback's picture: an image in TensorBoard, and the PNG beside the CSV log
    (image,) = acc.Images("bev/sample_0")
    png = next((run / "logs" / "version_0" / "bev").glob("*.png"))
    import matplotlib.image

    assert image.encoded_image_string.startswith(b"\x89PNG")
    assert (image.height, image.width) == matplotlib.image.imread(png).shape[:2]


@pytest.mark.skipif(not _has("mlflow"), reason="mlflow not installed")
def test_mlflow_logs_to_a_local_file_store(tmp_path):
    run = tmp_path / "run"
    run_config(BASELINE, run_dir=run, overrides=["trainer.log_every_n_steps=1", "trainer.loggers=[mlflow]"])
    losses = list((run / "mlruns").rglob("metrics/train/loss"))
    assert len(losses) == 1
    assert len(losses[0].read_text().split("\n")) >= 2  # one line per logged step
    assert (run / "logs" / "version_0" / "metrics.csv").is_file()  # CSV stays on


@pytest.mark.skipif(not _has("wandb"), reason="wandb not installed")
def test_wandb_runs_offline_under_the_run_dir(tmp_path):
    run = tmp_path / "run"
    run_config(BASELINE, run_dir=run, overrides=["trainer.log_every_n_steps=1", "trainer.loggers=[wandb]"])
    assert len(list((run / "wandb").glob("offline-run-*/run-*.wandb"))) == 1
    assert (run / "logs" / "version_0" / "metrics.csv").is_file()
