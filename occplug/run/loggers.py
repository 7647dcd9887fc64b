"""Experiment loggers by name (``trainer.loggers``), built from Lightning's own logger classes.

::

    trainer:
      loggers:
        - csv
        - tensorboard: {flush_secs: 30}
        - wandb: {project: myproj, entity: my-team, tags: [r50, occ3d], offline: false}
        - mlflow: {tracking_uri: "http://mlflow.internal:5000", experiment_name: duocc}

An entry is a name or a one-key mapping ``{name: settings}``; the settings are keyword arguments of
Lightning's logger class (``CSVLogger``, ``TensorBoardLogger``, ``MLFlowLogger``, ``WandbLogger``) and, for
the classes that pass further keywords on, of what they pass them to (TensorBoard's ``SummaryWriter``,
``wandb.init``: ``entity``, ``tags``, ``group``, ``mode``, ...). They are checked against those signatures at
config time (:func:`occplug.config.loggers.check_loggers`, re-exported here): a bad key is one line with the closest name.

CSV is always on (``<run>/logs/version_N/metrics.csv``, what ``occplug`` itself reads), whether
listed or not. The others write under the run directory too, and by default none reaches a server:
TensorBoard to ``<run>/tensorboard/version_N/``, MLflow to a local file store ``<run>/mlruns`` (unless
``tracking_uri`` names a server), Weights & Biases in its offline mode to ``<run>/wandb`` (``offline: false``
goes online; ``wandb sync`` uploads an offline run later). Where a logger writes (``save_dir``, and the CSV and
TensorBoard folder names) belongs to the run directory's layout, so those keys are refused. A logger whose
package is missing is one line naming the package to install.

Lightning also advertises its cloud services on every fit ("💡 Tip: ... litlogger"); that is
output a user did not ask for, so :func:`quiet_lightning_tips` filters it from Lightning's logger.
"""

from __future__ import annotations

import importlib.util
import logging
import os
from pathlib import Path
from typing import Any

from occplug.config.loggers import (
    LOGGERS,
    WANDB_INIT_ARGS,
    LoggerSpec,
    check_logger_names,
    check_loggers,
    logger_class,
)
from occplug.errors import ConfigError

__all__ = [
    "LOGGERS",
    "WANDB_INIT_ARGS",
    "LoggerSpec",
    "build_loggers",
    "check_logger_names",
    "check_loggers",
    "quiet_lightning_tips",
]


def _require(name: str) -> None:
    package = LOGGERS[name]
    if package is not None and importlib.util.find_spec(package) is None:
        raise ConfigError(
            f"trainer.loggers: '{name}' needs the {package} package, which is not installed: pip install {package}"
        )


def logger_arguments(spec: LoggerSpec, run_dir: Path) -> dict[str, Any]:
    """The keyword arguments :func:`build_loggers` gives ``spec``'s logger class: occplug's defaults under
    ``run_dir``, then the config's settings."""
    run_dir = Path(run_dir)
    settings = dict(spec.settings)
    if spec.name == "csv":
        # logs/version_<n>/: a resume never overwrites
        defaults: dict[str, Any] = {"save_dir": str(run_dir), "name": "logs"}
    elif spec.name == "tensorboard":
        defaults = {"save_dir": str(run_dir), "name": "tensorboard", "default_hp_metric": False}
    elif spec.name == "mlflow":
        store = (run_dir / "mlruns").absolute()
        defaults = {"experiment_name": "occplug", "run_name": run_dir.name, "tracking_uri": store.as_uri()}
        if settings.get("tracking_uri") is None:
            settings.pop("tracking_uri", None)
    else:  # wandb: offline unless the config says otherwise (offline: false, or a wandb.init mode)
        defaults = {"save_dir": str(run_dir), "name": run_dir.name, "project": "occplug"}
        defaults["offline"] = "mode" not in settings
    return {**defaults, **settings}


def build_loggers(value: Any, run_dir: Path) -> list[Any]:
    """The run's Lightning loggers: CSV first (always), then the named ones, all under ``run_dir``.

    Raises:
        ConfigError: an unknown name or setting, or a logger whose package is not installed (checked for
            every entry before any logger is built, so nothing is written).
    """
    from lightning.fabric.utilities.exceptions import MisconfigurationException

    specs = check_loggers(value)
    for spec in specs:
        _require(spec.name)
    if not any(spec.name == "csv" for spec in specs):
        specs.insert(0, LoggerSpec("csv", {}))
    specs.sort(key=lambda spec: spec.name != "csv")  # CSV first: what occplug reads back
    out: list[Any] = []
    for spec in specs:
        kwargs = logger_arguments(spec, run_dir)
        if spec.name == "mlflow" and kwargs["tracking_uri"].startswith("file:"):
            os.environ.setdefault("MLFLOW_ALLOW_FILE_STORE", "true")  # MLflow 3 refuses file stores unless told
        try:
            out.append(logger_class(spec.name)(**kwargs))
        except (ValueError, TypeError, MisconfigurationException) as exc:  # e.g. wandb's log_model while offline
            text = " ".join(str(exc).split()) or type(exc).__name__
            raise ConfigError(f"trainer.loggers: {spec.name}: {text}") from None
    return out


class _TipFilter(logging.Filter):
    """Drops Lightning's advertisements ("💡 Tip: ... litlogger / litmodels")."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        return not (message.startswith("💡 Tip") or "litlogger" in message or "litmodels" in message)


_TIP_FILTER = _TipFilter()
#: Loggers Lightning's ``rank_zero_info`` writes through (the pytorch one is the one in use).
_RANK_ZERO_LOGGERS = ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero")


def quiet_lightning_tips() -> None:
    """Filter Lightning's advertisements from its console log (idempotent)."""
    for name in _RANK_ZERO_LOGGERS:
        logger = logging.getLogger(name)
        if _TIP_FILTER not in logger.filters:
            logger.addFilter(_TIP_FILTER)
