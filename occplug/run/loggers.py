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
config time (:func:`check_loggers`): a bad key is one line with the closest name.

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
import inspect
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from occplug.errors import ConfigError
from occplug.registry import closest

__all__ = [
    "LOGGERS",
    "WANDB_INIT_ARGS",
    "LoggerSpec",
    "build_loggers",
    "check_logger_names",
    "check_loggers",
    "quiet_lightning_tips",
]

#: Logger names ``trainer.loggers`` accepts, with the Python package each needs (None: Lightning's own).
LOGGERS: dict[str, str | None] = {"csv": None, "tensorboard": "tensorboard", "mlflow": "mlflow", "wandb": "wandb"}

#: Lightning's logger class of each name (in ``lightning.pytorch.loggers``).
_CLASSES = {"csv": "CSVLogger", "tensorboard": "TensorBoardLogger", "mlflow": "MLFlowLogger", "wandb": "WandbLogger"}

#: Arguments occplug sets itself: where each logger writes is part of the run directory's layout.
_RESERVED: dict[str, tuple[str, ...]] = {
    "csv": ("save_dir", "name", "version"),
    "tensorboard": ("save_dir", "root_dir", "name", "version", "log_dir"),
    "mlflow": ("save_dir",),
    "wandb": ("save_dir", "dir", "experiment"),
}

#: The keyword arguments of ``wandb.init`` (wandb 0.19), for checking ``wandb`` settings where wandb is not
#: installed; where it is, its own signature is read instead.
WANDB_INIT_ARGS = (
    "entity", "project", "dir", "id", "name", "notes", "tags", "config", "config_exclude_keys",
    "config_include_keys", "allow_val_change", "group", "job_type", "mode", "force", "anonymous", "reinit",
    "resume", "resume_from", "fork_from", "save_code", "tensorboard", "sync_tensorboard", "monitor_gym",
    "settings",
)  # fmt: skip


@dataclass(frozen=True)
class LoggerSpec:
    """One ``trainer.loggers`` entry: the logger's name and its settings (keyword arguments)."""

    name: str
    settings: dict[str, Any]


def _logger_class(name: str) -> type:
    import lightning.pytorch.loggers as loggers  # importable without the logger's own package

    return getattr(loggers, _CLASSES[name])


def _passed_on(name: str) -> Callable[..., Any] | tuple[str, ...] | None:
    """What a logger class hands its ``**kwargs`` to (a callable, a table of names), or None."""
    if name == "wandb":
        if importlib.util.find_spec("wandb") is None:
            return WANDB_INIT_ARGS
        import wandb

        return wandb.init
    if name == "tensorboard":
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:
            return None  # no tensorboard: build_loggers names the package to install
        return SummaryWriter
    return None


def _allowed(name: str) -> dict[str, Any]:
    """``{argument: annotation}`` a logger's settings may set (its class's, then what its kwargs reach)."""
    from occplug.slots import component_params

    allowed = {k: hint for k, (_, hint) in component_params(_logger_class(name)).items()}
    target = _passed_on(name)
    if isinstance(target, tuple):
        allowed.update({k: inspect.Parameter.empty for k in target if k not in allowed})
    elif target is not None:
        allowed.update({k: hint for k, (_, hint) in component_params(target).items() if k not in allowed})
    for key in _RESERVED[name]:
        allowed.pop(key, None)
    return allowed


def _check_settings(
    name: str, settings: Any, key: str, check_type: Callable[[Any, Any], bool] | None
) -> dict[str, Any]:
    if settings is None:
        return {}
    if not isinstance(settings, dict):
        raise ConfigError(f"{key}: expected a mapping of {_CLASSES[name]} arguments, got {settings!r}")
    allowed = _allowed(name)
    for arg, value in settings.items():
        if arg in _RESERVED[name]:
            raise ConfigError(
                f"{key}.{arg}: set by occplug (every logger writes under the run directory; choose it with --run-dir)"
            )
        if arg not in allowed:
            hint = closest(str(arg), list(allowed))
            raise ConfigError(
                f"{key}.{arg}: unknown {name} logger argument{f'; did you mean {hint!r}?' if hint else ''} "
                f"(see lightning.pytorch.loggers.{_CLASSES[name]})"
            )
        annotation = allowed[arg]
        if check_type is not None and annotation is not inspect.Parameter.empty and not check_type(value, annotation):
            raise ConfigError(f"{key}.{arg}: {value!r} does not fit {_CLASSES[name]}'s {arg} argument")
    return dict(settings)


def check_loggers(
    value: Any, key: str = "trainer.loggers", check_type: Callable[[Any, Any], bool] | None = None
) -> list[LoggerSpec]:
    """``value`` as logger specs, each name known and each setting an argument of its logger (and, given
    ``check_type(value, annotation)`` -- the config validator's -- of its argument's type).

    Raises:
        ConfigError: one line naming the first bad entry (``trainer.loggers.1.wandb.projct: ...``).
    """
    if value is None:
        return []
    if isinstance(value, (str, dict)) or not isinstance(value, (list, tuple)):
        raise ConfigError(
            f"{key}: expected a list of logger names or {{name: settings}} (e.g. [csv, {{wandb: {{project: p}}}}]), "
            f"got {value!r}"
        )
    specs: dict[str, LoggerSpec] = {}
    for i, entry in enumerate(value):
        settings: Any = None
        if isinstance(entry, dict):
            if len(entry) != 1:
                raise ConfigError(f"{key}.{i}: expected one {{name: settings}} pair, got {entry!r}")
            ((entry, settings),) = entry.items()
        if entry not in LOGGERS:
            hint = closest(str(entry), list(LOGGERS))
            raise ConfigError(
                f"{key}.{i}: unknown logger {entry!r}{f'; did you mean {hint!r}?' if hint else ''} "
                f"(one of: {', '.join(LOGGERS)})"
            )
        checked = _check_settings(entry, settings, f"{key}.{i}.{entry}", check_type)
        if entry in specs and checked and specs[entry].settings and checked != specs[entry].settings:
            raise ConfigError(f"{key}.{i}: {entry!r} is listed twice with different settings")
        if entry not in specs or checked:
            specs[entry] = LoggerSpec(entry, checked)
    return list(specs.values())


def check_logger_names(value: Any, key: str = "trainer.loggers") -> list[str]:
    """The logger names of ``value`` (see :func:`check_loggers`, which this runs)."""
    return [spec.name for spec in check_loggers(value, key)]


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
            out.append(_logger_class(spec.name)(**kwargs))
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
