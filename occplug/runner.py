"""Programmatic runs: the same code paths the CLI uses (``occplug.testing.run_config`` too).

A run directory holds::

    config.yaml          the fully resolved config (re-usable with -c)
    plugins.json         installed plugins and their versions
    checkpoints/         last.ckpt (+ per-epoch checkpoints as configured)
    logs/version_0/      Lightning's CSV log (metrics.csv); each --resume adds a version
    metrics.json         final validation metrics (flat: {"mIoU": ..., "IoU": ..., ...})
"""

from __future__ import annotations

import datetime as _dt
import inspect
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
import yaml
from lightning.pytorch.callbacks import BasePredictionWriter, Callback, ModelCheckpoint
from lightning.pytorch.loggers import CSVLogger

from occplug.config import ConfigError, compose, validate
from occplug.data.datamodule import OccDataModule
from occplug.model import OccModel
from occplug.plugins import get_registry, plugin_reports

__all__ = [
    "build_datamodule",
    "build_model",
    "evaluate",
    "fit",
    "is_rank_zero",
    "load_checkpoint",
    "load_config",
    "plugin_versions",
    "predict",
]

CHECKPOINT_KEY = "occplug"


class RunError(Exception):
    """A user-facing problem with a run (exit code 2 from the CLI)."""


def load_config(refs: Sequence[str], overrides: Sequence[str] = (), saved: dict | None = None) -> dict[str, Any]:
    """Compose, resolve and validate a config (raises :class:`~occplug.config.ConfigError`)."""
    composed = compose(refs, overrides, data=saved)
    cfg = composed.resolved()
    validate(cfg, get_registry())
    return cfg


def plugin_versions() -> dict[str, str | None]:
    """``{plugin name: distribution version}`` of every loaded plugin."""
    return {r.name: r.version for r in plugin_reports() if r.error is None}


def build_datamodule(cfg: dict[str, Any]) -> OccDataModule:
    """The data module of ``cfg['data']``."""
    dm = get_registry().build("data", cfg["data"])
    if not isinstance(dm, OccDataModule):
        raise TypeError(f"data '{cfg['data']['type']}' built a {type(dm).__name__}, not an OccDataModule")
    return dm


def build_model(cfg: dict[str, Any], dm: OccDataModule) -> L.LightningModule:
    """The model of ``cfg['model']``, given the data module's classes and the config's grid."""
    grid = cfg.get("grid") or dm.grid.to_dict()
    model = get_registry().build(
        "model",
        cfg["model"],
        grid=grid,
        class_names=list(dm.class_names) or None,
        free_label=dm.free_label,
        ignore_label=dm.ignore_label,
        optimizer=cfg.get("optimizer"),
        scheduler=cfg.get("scheduler"),
        metrics=metric_nodes(cfg.get("metrics"), grid),
    )
    model.run_config = cfg  # stored in every checkpoint (self-contained checkpoints)
    return model


def metric_nodes(specs: list | None, grid: dict[str, Any]) -> list | None:
    """The config's ``metrics`` as nodes, with the run's ``grid`` filled into metrics that take one
    (e.g. ``rayiou``) and do not set it."""
    if specs is None:
        return None
    out = []
    for spec in specs:
        node = {"type": spec} if isinstance(spec, str) else dict(spec)
        factory = get_registry().get("metric", node["type"]).factory
        if "grid" not in node and "grid" in inspect.signature(factory).parameters:
            node["grid"] = grid
        out.append(node)
    return out


class _RunInfoCallback(Callback):
    """Stores the resolved config and plugin versions in every checkpoint; tracks validations."""

    def __init__(self, cfg: dict[str, Any]) -> None:
        self.cfg = cfg
        self.last_val_step = -1

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict) -> None:
        checkpoint[CHECKPOINT_KEY] = {"config": self.cfg, "plugins": plugin_versions()}

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not trainer.sanity_checking:
            self.last_val_step = trainer.global_step


class _NpzPredictionWriter(BasePredictionWriter):
    def __init__(self, out: Path) -> None:
        super().__init__(write_interval="batch")
        self.out = out

    def write_on_batch_end(self, trainer, pl_module, prediction, batch_indices, batch, batch_idx, dataloader_idx):  # type: ignore[override]
        for token, pred in zip(prediction["token"], prediction["pred"], strict=True):
            tmp = self.out / f".{token}.tmp.npz"
            np.savez_compressed(tmp, pred=pred.to(torch.uint8).cpu().numpy())
            os.replace(tmp, self.out / f"{token}.npz")


def build_callbacks(cfg: dict[str, Any]) -> list[Callback]:
    """The Lightning callbacks named in the config's ``callbacks:`` mapping (``null`` entries are off)."""
    out = []
    for name, node in (cfg.get("callbacks") or {}).items():
        if node is None:
            continue
        callback = get_registry().build("callback", node)
        if not isinstance(callback, Callback):
            raise TypeError(f"callbacks.{name}: '{node['type']}' built a {type(callback).__name__}, not a lightning Callback")
        out.append(callback)
    return out


def _trainer(cfg: dict[str, Any], root: Path | None, callbacks: list[Callback], logger: Any = False) -> L.Trainer:
    kwargs = dict(cfg.get("trainer") or {})
    try:
        callbacks = [*callbacks, *build_callbacks(cfg)]
    except (ValueError, TypeError) as exc:
        raise RunError(str(exc).splitlines()[0]) from None
    kwargs.setdefault("enable_model_summary", False)
    if root is not None:
        kwargs["default_root_dir"] = str(root)
    return L.Trainer(callbacks=callbacks, logger=logger, **kwargs)


#: Rank 0's run directory, for the processes a DDP launcher re-runs with the same command line
#: (their clock would name another default directory).
RUN_DIR_ENV = "OCCPLUG_RANK_ZERO_RUN_DIR"


def is_rank_zero() -> bool:
    """Whether this process is global rank 0 as far as a launcher has announced ranks.

    Reads what launchers set before any process group exists: ``RANK`` (torchrun), then
    ``LOCAL_RANK`` with ``NODE_RANK``/``GROUP_RANK`` (Lightning's DDP re-launch sets these in the
    processes it starts), then ``SLURM_PROCID``; a process no launcher started is rank 0.
    """
    env = os.environ
    if "RANK" in env:
        return int(env["RANK"]) == 0
    if "LOCAL_RANK" in env:
        return int(env["LOCAL_RANK"]) == 0 and int(env.get("NODE_RANK", env.get("GROUP_RANK", 0))) == 0
    return int(env.get("SLURM_PROCID", 0)) == 0


def default_run_dir(refs: Sequence[str]) -> Path:
    """``runs/<YYYYmmdd-HHMMSS>-<first config name>`` (in a DDP worker process: rank 0's directory)."""
    if not is_rank_zero() and os.environ.get(RUN_DIR_ENV):
        return Path(os.environ[RUN_DIR_ENV])
    stem = Path(refs[0]).stem if refs else "run"
    return Path("runs") / f"{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}-{stem}"


def fit(cfg: dict[str, Any], run_dir: Path, resume: bool = False) -> dict[str, float]:
    """Train per ``cfg`` into ``run_dir``; return the final validation metrics.

    Everything is built before anything is written, so a configuration mistake leaves no
    half-made run directory. Under a multi-process strategy (e.g. ``trainer.strategy=ddp``) every
    rank runs this function; only global rank 0 checks and writes ``run_dir``.
    """
    run_dir = Path(run_dir)
    ckpt_dir = run_dir / "checkpoints"
    last = ckpt_dir / "last.ckpt"
    if resume and not last.is_file():
        raise RunError(f"--resume {run_dir}: no checkpoint at {last}")
    if is_rank_zero():
        if not resume and run_dir.exists() and any(run_dir.iterdir()):
            raise RunError(f"run directory {run_dir} already exists and is not empty; choose another --run-dir or --resume it")
        os.environ[RUN_DIR_ENV] = str(run_dir.absolute())  # inherited by the ranks a DDP launcher starts
    L.seed_everything(int(cfg.get("seed", 0)), workers=True, verbose=False)
    dm, model = _build(cfg)
    info = _RunInfoCallback(cfg)
    checkpoint = ModelCheckpoint(dirpath=str(ckpt_dir), **{"save_last": True, **(cfg.get("checkpoint") or {})})
    logger = CSVLogger(save_dir=str(run_dir), name="logs")  # logs/version_<n>/: a resume never overwrites
    trainer = _trainer(cfg, run_dir, [checkpoint, info], logger)
    if trainer.is_global_zero:
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "config.yaml").write_text(
            "# resolved occplug config; plugins and versions in plugins.json\n"
            + yaml.safe_dump(cfg, sort_keys=False, default_flow_style=None)
        )
        (run_dir / "plugins.json").write_text(json.dumps(plugin_versions(), indent=2) + "\n")
    trainer.fit(model, datamodule=dm, ckpt_path=str(last) if resume else None)
    if info.last_val_step != trainer.global_step:  # training stopped between validations
        trainer.validate(model, datamodule=dm, verbose=False)
    results = dict(model.last_results.get("val", {}))
    if trainer.is_global_zero:
        payload = {**results, "global_step": trainer.global_step, "epoch": trainer.current_epoch}
        (run_dir / "metrics.json").write_text(json.dumps(payload, indent=2) + "\n")
        for table in model.last_tables.values():
            if table:
                print(table)
    return results


def load_checkpoint(path: Path) -> dict[str, Any]:
    """Read a checkpoint with ``weights_only=True``; clear errors for a missing or foreign file."""
    path = Path(path)
    if not path.is_file():
        raise RunError(f"checkpoint {path} does not exist")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise RunError(f"checkpoint {path} cannot be read safely (weights_only=True): {str(exc).splitlines()[0]}") from None


def config_from_checkpoint(ckpt: dict[str, Any], path: Path) -> dict[str, Any]:
    """The resolved config stored in an occplug checkpoint."""
    info = ckpt.get(CHECKPOINT_KEY)
    if not isinstance(info, dict) or "config" not in info:
        raise RunError(f"checkpoint {path} carries no occplug config; pass -c CONFIG")
    return info["config"]


def _build(cfg: dict[str, Any]) -> tuple[OccDataModule, L.LightningModule]:
    """Data module and model; a component rejecting its arguments is a user-facing error."""
    try:
        dm = build_datamodule(cfg)
        return dm, build_model(cfg, dm)
    except (ValueError, TypeError, FileNotFoundError, ImportError) as exc:
        raise RunError(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None


def _restore(cfg: dict[str, Any], ckpt: dict[str, Any], path: Path) -> tuple[OccDataModule, L.LightningModule]:
    dm, model = _build(cfg)
    try:
        model.load_state_dict(ckpt["state_dict"])
    except (KeyError, RuntimeError) as exc:
        raise RunError(f"checkpoint {path} does not match the configured model: {str(exc).splitlines()[0]}") from None
    return dm, model


def evaluate(cfg: dict[str, Any], ckpt_path: Path, stage: str = "validate") -> tuple[dict[str, float], dict[str, str]]:
    """Evaluate a checkpoint; return ``(metrics, per-metric tables)``."""
    ckpt = load_checkpoint(ckpt_path)
    dm, model = _restore(cfg, ckpt, ckpt_path)
    trainer = _trainer(cfg, None, [])
    if stage == "validate":
        trainer.validate(model, datamodule=dm, verbose=False)
        return dict(model.last_results.get("val", {})), dict(model.last_tables)
    trainer.test(model, datamodule=dm, verbose=False)
    return dict(model.last_results.get("test", {})), dict(model.last_tables)


def predict(cfg: dict[str, Any], ckpt_path: Path, out: Path) -> int:
    """Write ``<out>/<token>.npz`` (key ``pred``: ``(X, Y, Z)`` uint8 class ids) per sample; return the count."""
    ckpt = load_checkpoint(ckpt_path)
    dm, model = _restore(cfg, ckpt, ckpt_path)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    trainer = _trainer(cfg, None, [_NpzPredictionWriter(out)])
    trainer.predict(model, datamodule=dm, return_predictions=False)
    return len(list(out.glob("*.npz")))


def resolve_run_config(refs: Sequence[str], overrides: Sequence[str], ckpt: Path | None = None) -> dict[str, Any]:
    """Config for validate/test/predict: ``-c`` files if given, else the checkpoint's own config."""
    if refs:
        return load_config(refs, overrides)
    if ckpt is None:
        raise ConfigError("no -c CONFIG given")
    saved = config_from_checkpoint(load_checkpoint(ckpt), ckpt)
    return load_config([], overrides, saved=saved)
