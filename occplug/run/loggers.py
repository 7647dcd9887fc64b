"""Experiment loggers by name (``trainer.loggers``), built from Lightning's own logger classes.

::

    trainer:
      loggers: [csv, tensorboard]      # also: mlflow, wandb

CSV is always on (``<run>/logs/version_N/metrics.csv``, what ``occplug`` itself reads), whether
listed or not. The others write under the run directory too, and none reaches a server:
TensorBoard to ``<run>/tensorboard/version_N/``, MLflow to a local file store ``<run>/mlruns``,
Weights & Biases in its offline mode to ``<run>/wandb`` (``wandb sync`` uploads it later).
A logger whose package is missing is one line naming the package to install.

Lightning also advertises its cloud services on every fit ("💡 Tip: ... litlogger"); that is
output a user did not ask for, so :func:`quiet_lightning_tips` filters it from Lightning's logger.
"""

from __future__ import annotations

import importlib.util
import logging
import os
from pathlib import Path
from typing import Any

from occplug.errors import ConfigError
from occplug.registry import closest

__all__ = ["LOGGERS", "build_loggers", "check_logger_names", "quiet_lightning_tips"]

#: Logger names ``trainer.loggers`` accepts, with the Python package each needs (None: Lightning's own).
LOGGERS: dict[str, str | None] = {"csv": None, "tensorboard": "tensorboard", "mlflow": "mlflow", "wandb": "wandb"}


def check_logger_names(value: Any, key: str = "trainer.loggers") -> list[str]:
    """``value`` as a list of known logger names; :class:`ConfigError` naming the first bad entry."""
    if value is None:
        return []
    if isinstance(value, str) or not isinstance(value, (list, tuple)):
        raise ConfigError(f"{key}: expected a list of logger names (e.g. [csv, tensorboard]), got {value!r}")
    names: list[str] = []
    for i, name in enumerate(value):
        if name not in LOGGERS:
            hint = closest(str(name), list(LOGGERS))
            raise ConfigError(
                f"{key}.{i}: unknown logger {name!r}{f'; did you mean {hint!r}?' if hint else ''} "
                f"(one of: {', '.join(LOGGERS)})"
            )
        if name not in names:
            names.append(name)
    return names


def _require(name: str) -> None:
    package = LOGGERS[name]
    if package is not None and importlib.util.find_spec(package) is None:
        raise ConfigError(
            f"trainer.loggers: '{name}' needs the {package} package, which is not installed: pip install {package}"
        )


def build_loggers(names: Any, run_dir: Path) -> list[Any]:
    """The run's Lightning loggers: CSV first (always), then the named ones, all under ``run_dir``.

    Raises:
        ConfigError: an unknown name, or a logger whose package is not installed (checked for
            every name before any logger is built, so nothing is written).
    """
    from lightning.pytorch.loggers import CSVLogger

    chosen = check_logger_names(names)
    for name in chosen:
        _require(name)
    run_dir = Path(run_dir)
    out: list[Any] = [CSVLogger(save_dir=str(run_dir), name="logs")]  # logs/version_<n>/: a resume never overwrites
    for name in chosen:
        if name == "tensorboard":
            from lightning.pytorch.loggers import TensorBoardLogger

            out.append(TensorBoardLogger(save_dir=str(run_dir), name="tensorboard", default_hp_metric=False))
        elif name == "mlflow":
            from lightning.pytorch.loggers import MLFlowLogger

            store = (run_dir / "mlruns").absolute()
            os.environ.setdefault("MLFLOW_ALLOW_FILE_STORE", "true")  # MLflow 3 refuses file stores unless told
            out.append(MLFlowLogger(experiment_name="occplug", run_name=run_dir.name, tracking_uri=store.as_uri()))
        elif name == "wandb":
            from lightning.pytorch.loggers import WandbLogger

            out.append(WandbLogger(save_dir=str(run_dir), name=run_dir.name, project="occplug", offline=True))
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
