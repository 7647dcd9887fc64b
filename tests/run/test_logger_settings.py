"""``trainer.loggers`` entries with settings, passed through to Lightning's logger classes and checked against
their signatures (W&B and MLflow through recording subclasses: neither package is needed, nothing goes online)."""

from __future__ import annotations

import importlib.util
import inspect
from pathlib import Path

import lightning.pytorch.loggers as pl_loggers
import pytest
from lightning.pytorch.loggers import CSVLogger, MLFlowLogger, TensorBoardLogger, WandbLogger

from occplug.cli import main
from occplug.config import ConfigError
from occplug.config.validate import check_type
from occplug.run import loggers, runner
from occplug.run.loggers import LoggerSpec, build_loggers, check_loggers

ROOT = Path(__file__).resolve().parents[2]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
DEBUG = "occplug/trainer/debug"


@pytest.fixture
def recorded(monkeypatch):
    """Replace W&B's and MLflow's logger classes by subclasses that record their keyword arguments (the
    signature the settings are checked against stays the real class's, through the subclass's ``**kwargs``)."""
    seen: dict[str, dict] = {}

    def recorder(base: type, name: str) -> type:
        class Recorder(base):
            def __init__(self, **kwargs) -> None:  # no super().__init__: no package, no files
                seen[name] = kwargs

        return Recorder

    monkeypatch.setattr(pl_loggers, "WandbLogger", recorder(WandbLogger, "wandb"))
    monkeypatch.setattr(pl_loggers, "MLFlowLogger", recorder(MLFlowLogger, "mlflow"))
    monkeypatch.setattr(loggers, "_require", lambda name: None)
    return seen


def test_wandb_settings_pass_through_and_the_run_stays_offline_unless_told(tmp_path, recorded):
    cfg = runner.load_config([BASELINE], ["trainer.loggers=[{wandb: {project: myproj, entity: team, tags: [r50, a]}}]"])
    built = build_loggers(cfg["trainer"]["loggers"], tmp_path / "run")
    assert isinstance(built[0], CSVLogger) and len(built) == 2  # CSV first, always
    assert recorded["wandb"] == {
        "save_dir": str(tmp_path / "run"),
        "name": "run",
        "project": "myproj",
        "offline": True,
        "entity": "team",  # wandb.init's, through WandbLogger's **kwargs
        "tags": ["r50", "a"],
    }
    build_loggers([{"wandb": {"offline": False, "group": "sweep"}}], tmp_path / "run")
    assert recorded["wandb"]["offline"] is False and recorded["wandb"]["project"] == "occplug"
    build_loggers([{"wandb": {"mode": "online"}}], tmp_path / "run")  # wandb.init's mode decides
    assert recorded["wandb"]["offline"] is False and recorded["wandb"]["mode"] == "online"


def test_mlflow_takes_a_tracking_uri_and_defaults_to_a_file_store_in_the_run(tmp_path, recorded):
    build_loggers([{"mlflow": {"tracking_uri": "http://mlflow.internal:5000", "tags": {"grid": "occ3d"}}}], tmp_path)
    assert recorded["mlflow"] == {
        "experiment_name": "occplug",
        "run_name": tmp_path.name,
        "tracking_uri": "http://mlflow.internal:5000",
        "tags": {"grid": "occ3d"},
    }
    build_loggers(["mlflow"], tmp_path)
    assert recorded["mlflow"]["tracking_uri"] == (tmp_path / "mlruns").absolute().as_uri()


@pytest.mark.skipif(importlib.util.find_spec("tensorboard") is None, reason="tensorboard not installed")
def test_tensorboard_and_csv_settings_reach_the_real_classes(tmp_path):
    built = build_loggers(
        ["tensorboard", {"tensorboard": {"flush_secs": 7, "prefix": "occ"}}, {"csv": {"flush_logs_every_n_steps": 3}}],
        tmp_path,
    )
    csv, tb = built
    assert isinstance(csv, CSVLogger) and isinstance(tb, TensorBoardLogger)
    assert csv._flush_logs_every_n_steps == 3 and Path(csv.log_dir) == tmp_path / "logs" / "version_0"
    assert tb._prefix == "occ" and tb._kwargs == {"flush_secs": 7}  # SummaryWriter's, through **kwargs
    assert Path(tb.log_dir) == tmp_path / "tensorboard" / "version_0" and not tb._default_hp_metric


@pytest.mark.parametrize(
    ("value", "line"),
    [
        (
            [{"wandb": {"projct": "x"}}],
            "trainer.loggers.0.wandb.projct: unknown wandb logger argument; did you mean 'project'? "
            "(see lightning.pytorch.loggers.WandbLogger)",
        ),
        (
            ["csv", {"mlflow": {"tracking_url": "http://h"}}],
            "trainer.loggers.1.mlflow.tracking_url: unknown mlflow logger argument; did you mean 'tracking_uri'?",
        ),
        ([{"tensorboard": {"flush_sec": 5}}], "trainer.loggers.0.tensorboard.flush_sec: unknown tensorboard logger "
                                              "argument; did you mean 'flush_secs'?"),
        ([{"csv": {"name": "mine"}}], "trainer.loggers.0.csv.name: set by occplug (every logger writes under the run"),
        ([{"wandb": {"save_dir": "/tmp/x"}}], "trainer.loggers.0.wandb.save_dir: set by occplug"),
        ([{"csv": {"flush_logs_every_n_steps": "often"}}],
         "trainer.loggers.0.csv.flush_logs_every_n_steps: 'often' does not fit CSVLogger's flush_logs_every_n_steps"),
        ([{"wandb": "myproj"}], "trainer.loggers.0.wandb: expected a mapping of WandbLogger arguments, got 'myproj'"),
        ([{"wandb": {}, "csv": {}}], "trainer.loggers.0: expected one {name: settings} pair"),
        ([{"wandbb": {"project": "p"}}], "trainer.loggers.0: unknown logger 'wandbb'; did you mean 'wandb'?"),
        ({"wandb": {"project": "p"}}, "trainer.loggers: expected a list of logger names or {name: settings}"),
    ],
)  # fmt: skip
def test_a_bad_setting_is_one_line_with_the_closest_name(value, line):
    with pytest.raises(ConfigError) as err:
        check_loggers(value, check_type=check_type)  # as config validation runs it
    assert str(err.value).startswith(line) and "\n" not in str(err.value), str(err.value)


def test_the_cli_refuses_a_bad_key_before_anything_is_written(tmp_path, capsys):
    run = tmp_path / "run"
    code = main(["fit", "-c", BASELINE, "-c", DEBUG, "--run-dir", str(run), "trainer.loggers=[{wandb: {projct: p}}]"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and not run.exists()
    assert err == [
        "error: trainer.loggers.0.wandb.projct: unknown wandb logger argument; did you mean 'project'? "
        "(see lightning.pytorch.loggers.WandbLogger)"
    ]


def test_names_and_settings_merge_one_entry_per_logger():
    assert check_loggers(["csv", "tensorboard", {"tensorboard": {"flush_secs": 5}}, "csv"]) == [
        LoggerSpec("csv", {}),
        LoggerSpec("tensorboard", {"flush_secs": 5}),
    ]
    with pytest.raises(ConfigError, match=r"^trainer.loggers.1: 'csv' is listed twice with different settings"):
        check_loggers([{"csv": {"prefix": "a"}}, {"csv": {"prefix": "b"}}])


@pytest.mark.skipif(importlib.util.find_spec("wandb") is None, reason="wandb not installed")
def test_the_wandb_table_is_wandb_inits_signature():
    import wandb

    params = inspect.signature(wandb.init).parameters
    assert set(loggers.WANDB_INIT_ARGS) == {k for k, p in params.items() if p.kind is not p.VAR_KEYWORD}
