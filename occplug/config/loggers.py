"""The logger vocabulary of a config (``trainer.loggers``): the names, their settings and how they are checked.

The config validator checks ``trainer.loggers`` with :func:`check_loggers` (so ``config/`` needs nothing of
``run/``); :mod:`occplug.run.loggers` builds the loggers from the checked specs (its docstring describes the
settings and where each logger writes).
"""

from __future__ import annotations

import importlib.util
import inspect
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from occplug.errors import ConfigError, closest

__all__ = ["LOGGERS", "WANDB_INIT_ARGS", "LoggerSpec", "check_logger_names", "check_loggers", "logger_class"]

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


def logger_class(name: str) -> type:
    """Lightning's logger class of ``name`` (imported on use)."""
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

    allowed = {k: hint for k, (_, hint) in component_params(logger_class(name)).items()}
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
