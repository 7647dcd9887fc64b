"""Programmatic runs: the same code paths the CLI uses (``occplug.testing.run_config`` too).

A run directory holds::

    config.yaml          the fully resolved config (re-usable with -c)
    plugins.json         installed plugins and their versions
    environment.json     what the numbers depend on besides the code: torch and its CPU kernel set, the CPU,
                         the numeric packages' versions (numeric_environment)
    checkpoints/         last.ckpt (+ per-epoch checkpoints as configured; every N steps with
                         trainer.checkpoint_every_n_steps)
    logs/version_0/      Lightning's CSV log (metrics.csv); each --resume adds a version
    tensorboard/ mlruns/ wandb/   the other trainer.loggers, when the config names them
    metrics.json         final validation metrics (flat: {"mIoU": ..., "IoU": ..., ...})

Every file of it is written atomically (a temporary file in the same folder, then a rename), so a
run killed at any moment leaves each file whole: the old version or the new one.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import math
import os
import sys
import tempfile
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from lightning.fabric.plugins import TorchCheckpointIO
from lightning.fabric.utilities.exceptions import MisconfigurationException
from lightning.pytorch.callbacks import BasePredictionWriter, Callback, ModelCheckpoint

from occplug.config import ConfigError, compose, validate
from occplug.config.defaults import run_config_text
from occplug.context import RunContext, parse_grid
from occplug.data.classes import class_groups
from occplug.data.datamodule import OccDataModule
from occplug.data.formats import FormatError
from occplug.errors import UserError
from occplug.interfaces.model import OccupancyModel
from occplug.plugins import get_registry, plugin_reports
from occplug.run import preflight, ranks
from occplug.run.checkpoints import RunError, RunInterrupted, WriteError, check_resume_checkpoint, load_checkpoint
from occplug.run.loggers import build_loggers, quiet_lightning_tips
from occplug.run.rundir import (
    SignalCheckpoint,
    check_fresh_run_dir,
    confined_checkpoint_node,
    interruptible,
    read_run_config,
    remove_stale_temporaries,
    run_lock,
    temporary_prefix,
)
from occplug.run.weights import init_from_config
from occplug.streams import check_streaming

__all__ = [
    "AtomicCheckpointIO",
    "RunError",
    "RunInterrupted",
    "WriteError",
    "build_datamodule",
    "build_model",
    "build_run",
    "config_from_checkpoint",
    "data_errors",
    "Evaluation",
    "evaluate",
    "fit",
    "is_rank_zero",
    "load_checkpoint",
    "load_config",
    "NUMERIC_PACKAGES",
    "cpu_name",
    "numeric_environment",
    "plugin_versions",
    "predict",
    "read_run_config",
    "resolve_run_config",
    "restore_run",
    "run_context",
    "saved_run_config",
    "write_text_atomic",
]

CHECKPOINT_KEY = "occplug"


#: The evaluation mask when a config names none (the Occ3D-nuScenes convention).
DEFAULT_EVAL_MASK = "camera"


def load_config(refs: Sequence[str], overrides: Sequence[str] = (), saved: dict | None = None) -> dict[str, Any]:
    """Compose, resolve and validate a config (raises :class:`~occplug.config.ConfigError`).

    The evaluation mask is resolved into ``eval_mask`` (see :func:`resolve_eval_mask`), so the
    saved config, the checkpoint and ``metrics.json`` all name it.
    """
    composed = compose(refs, overrides, data=saved)
    cfg = composed.resolved()
    validate(cfg, get_registry())
    cfg["eval_mask"] = resolve_eval_mask(cfg)
    return cfg


def resolve_eval_mask(cfg: dict[str, Any]) -> str:
    """The run's one evaluation mask: ``eval_mask``, else ``model.eval_mask`` or a ``mask`` set on a metric node,
    else ``camera``. The model gives it to every metric that takes a ``mask`` (``given``).

    Raises:
        ConfigError: ``model.eval_mask`` or metric nodes set a mask that differs from ``eval_mask`` (or from each
            other).
    """
    chosen = cfg.get("eval_mask")
    source = "eval_mask"
    model = cfg.get("model")
    named = [("model.eval_mask", model.get("eval_mask"))] if isinstance(model, dict) else []
    named += [
        (f"metrics.{i}.mask", s.get("mask")) for i, s in enumerate(cfg.get("metrics") or []) if isinstance(s, dict)
    ]
    for where, mask in named:
        if mask is not None:
            if chosen is None:
                chosen, source = mask, where
            elif mask != chosen:
                raise ConfigError(
                    f"{where}: {mask!r} differs from {source}={chosen!r}; set the evaluation mask "
                    "once, with the top-level eval_mask"
                )
    return str(chosen if chosen is not None else DEFAULT_EVAL_MASK)


def saved_run_config(cfg: dict[str, Any]) -> dict[str, Any]:
    """``cfg`` as a run directory's ``config.yaml`` holds it (every component argument with its default, what
    :func:`fit` writes), so a script can tell whether a finished run is of the config a recipe composes today."""
    from occplug.config.yamlio import parse_yaml

    return parse_yaml(run_config_text(cfg), "config.yaml")


def plugin_versions() -> dict[str, str | None]:
    """``{plugin name: distribution version}`` of every loaded plugin."""
    return {r.name: r.version for r in plugin_reports() if r.error is None}


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what :mod:`platform` knows."""
    import platform

    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


#: The distributions whose versions :func:`numeric_environment` records (those a run's numbers can depend on).
NUMERIC_PACKAGES = ("torch", "lightning", "torchmetrics", "numpy", "kornia", "numba", "timm")


def numeric_environment() -> dict[str, Any]:
    """What a run's numbers depend on besides the code, seed and config, as plain data.

    The same code and seed give bit-identical CPU runs only on the same kernel set: torch picks its vectorised CPU
    kernels by the CPU's vector unit (``cpu_capability``: ``AVX2``, ``AVX512``, ...; ``ATEN_CPU_CAPABILITY`` lowers
    it), and each set rounds differently, so runs on two machines drift apart step by step. Recorded in every run
    directory (``environment.json``) and in every per-seed result file, so two numbers can be told apart by where
    they were made.
    """
    import platform
    from importlib.metadata import PackageNotFoundError, version

    import torch

    versions: dict[str, str | None] = {}
    for name in NUMERIC_PACKAGES:
        try:
            versions[name] = version(name)
        except PackageNotFoundError:
            versions[name] = None
    return {
        "cpu": cpu_name(),
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "machine": platform.machine(),
        "python": platform.python_version(),
        "torch_threads": torch.get_num_threads(),
        "cuda_device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "packages": versions,
    }


def build_datamodule(cfg: dict[str, Any]) -> OccDataModule:
    """The data module of ``cfg['data']``, given the run's top-level ``grid`` where the config has one."""
    given = {} if cfg.get("grid") is None else {"grid": cfg["grid"]}
    dm = get_registry().build("data", cfg["data"], **given)
    if not isinstance(dm, OccDataModule):
        raise TypeError(f"data '{cfg['data']['type']}' built a {type(dm).__name__}, not an OccDataModule")
    return dm


def run_context(cfg: dict[str, Any], dm: OccDataModule) -> RunContext:
    """The run's one :class:`~occplug.context.RunContext`: the config's ``grid`` (parsed here, once; the data
    module's own when the config has none), the data set's classes with their groups, its free and ignore ids,
    the evaluation mask and the registry the run's components are built from."""
    grid = parse_grid(cfg["grid"]) if cfg.get("grid") is not None else dm.grid
    return RunContext(
        grid=grid,
        class_names=tuple(dm.class_names),
        free_label=dm.free_label,
        ignore_label=dm.ignore_label,
        class_groups=class_groups(dm.class_names) or {},
        eval_mask=cfg.get("eval_mask") or DEFAULT_EVAL_MASK,
        registry=get_registry(),
    )


def build_model(cfg: dict[str, Any], dm: OccDataModule) -> OccupancyModel:
    """The model of ``cfg['model']``, built through the run context (:func:`run_context`), given its grid, classes
    and evaluation mask (``eval_mask``, which the model gives its metrics that take a ``mask``).

    The runner reads a model only through :class:`~occplug.interfaces.model.OccupancyModel`, so a
    plugin's own model class (kind ``model``) fits, validates, predicts and checkpoints the same way.
    """
    context = run_context(cfg, dm)
    model = context.build(
        "model",
        cfg["model"],
        grid=context.grid.to_dict(),  # a plugin's model may keep it as a hyper-parameter: plain data
        class_names=list(context.class_names) or None,
        free_label=context.free_label,
        ignore_label=context.ignore_label,
        optimizer=cfg.get("optimizer"),
        scheduler=cfg.get("scheduler"),
        metrics=cfg.get("metrics"),
        eval_mask=context.eval_mask,
    )
    model.run_config = cfg  # stored in every checkpoint (self-contained checkpoints)
    return model


def mask_settings(cfg: dict[str, Any], model: OccupancyModel) -> dict[str, Any]:
    """``{"eval_mask": ..., "train_masks": {supervision name: mask}}`` of a run (see README, Metrics)."""
    train = model.training_masks()
    return {"eval_mask": cfg.get("eval_mask") or DEFAULT_EVAL_MASK, "train_masks": train}


def describe_masks(masks: dict[str, Any]) -> str:
    """One line naming the evaluation and training masks, printed above every per-class table."""
    train = ", ".join(f"{name}: {mask}" for name, mask in masks["train_masks"].items()) or "(no supervision)"
    return f"evaluation mask: {masks['eval_mask']} | training masks: {train}"


def run_info(cfg: dict[str, Any], model: OccupancyModel, dm: OccDataModule) -> dict[str, Any]:
    """What a checkpoint carries besides the weights, so it rebuilds and explains itself alone.

    ``config`` (resolved), ``class_names``, ``grid``, ``masks`` (:func:`mask_settings`), ``plugins``
    (name -> version) and ``components`` (every ``type:`` the config uses with the plugin and
    distribution that provides it).
    """
    used = validate(cfg, get_registry())
    versions = plugin_versions()
    return {
        "config": cfg,
        "class_names": list(dm.class_names),
        "grid": dm.grid.to_dict() if cfg.get("grid") is None else dict(cfg["grid"]),
        "masks": mask_settings(cfg, model),
        "labels": dm.label_cut.describe(),
        "plugins": versions,
        "components": [
            {
                "path": u.path,
                "kind": u.kind,
                "type": u.type,
                "plugin": u.plugin,
                "distribution": u.distribution,
                "version": versions.get(u.plugin),
            }
            for u in used
        ],
    }


class _RunInfoCallback(Callback):
    """Stores :func:`run_info` in every checkpoint; tracks validations."""

    def __init__(self, info: dict[str, Any]) -> None:
        self.info = info
        self.last_val_step = -1
        self.last_saved_step = -1

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict) -> None:
        checkpoint[CHECKPOINT_KEY] = self.info
        self.last_saved_step = trainer.global_step

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
            raise TypeError(
                f"callbacks.{name}: '{node['type']}' built a {type(callback).__name__}, not a lightning Callback"
            )
        out.append(callback)
    return out


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same folder and a rename: a reader, or a
    run killed meanwhile, sees the old file or the new one, never a part."""
    _write_atomic(Path(path), lambda fh: fh.write(text.encode()))


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


#: Mode of the files written atomically (``mkstemp`` makes them private; plain ``open`` would not).
_FILE_MODE = 0o666 & ~_umask()


def _write_atomic(path: Path, write: Any) -> None:
    """``write(fh)`` into ``.<name>.<pid>.<random>.tmp`` beside ``path``, then a rename. Temporary files that
    killed writers left for ``path`` are removed first; a failing disk (full, read-only, a folder in the way) is
    one :class:`WriteError` line and keeps the previous file."""
    try:
        remove_stale_temporaries(path)
        fd, tmp = tempfile.mkstemp(prefix=temporary_prefix(path), suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise write_error(path, exc) from None
    try:
        os.fchmod(fd, _FILE_MODE)
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise write_error(path, exc) from None
        raise


def write_error(path: Path, exc: OSError) -> WriteError:
    """One line for a file that cannot be written: the file, the system's reason, and that the old one is kept."""
    reason = exc.strerror or str(exc) or type(exc).__name__
    kept = "; the previous version is kept" if Path(path).is_file() else ""
    if Path(path).is_dir():
        reason = "a folder is in the way"
    return WriteError(f"cannot write {path}: {reason}{kept}")


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning's ``torch.save`` checkpoint IO, each file written atomically (see :func:`write_text_atomic`):
    a fit killed while saving keeps its previous ``last.ckpt`` whole."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None) -> None:
        if storage_options is not None:
            raise TypeError(f"{type(self).__name__} takes no storage_options")
        path = Path(path)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise write_error(path, exc) from None
        _write_atomic(path, lambda fh: torch.save(checkpoint, fh))

    def load_checkpoint(self, path: Any, map_location: Any = None, weights_only: Any = None) -> dict[str, Any]:
        """Every checkpoint Lightning reads (``fit --resume``) goes through :func:`load_checkpoint`
        (``weights_only=True`` whatever the torch version or ``weights_only`` asked); the one handed over by
        :meth:`hand_over` is returned without reading it again."""
        handed, self._handed = getattr(self, "_handed", None), None
        if handed is not None and Path(handed[0]) == Path(path):
            return handed[1]
        return load_checkpoint(Path(path))

    def hand_over(self, path: Path, checkpoint: dict[str, Any]) -> None:
        """Give the next :meth:`load_checkpoint` of ``path`` this already read (and checked) checkpoint."""
        self._handed = (Path(path), checkpoint)


#: occplug's own ``trainer.*`` keys (validated with the Trainer's; see ``config.validate.TRAINER_EXTRAS``).
STEP_CHECKPOINT_KEY = "checkpoint_every_n_steps"


def step_checkpoint(cfg: dict[str, Any], ckpt_dir: Path) -> list[Callback]:
    """With ``trainer.checkpoint_every_n_steps: N``, a callback rewriting ``last.ckpt`` every N optimizer
    steps (beside the per-epoch checkpoints, which stay); else none."""
    every = (cfg.get("trainer") or {}).get(STEP_CHECKPOINT_KEY)
    if every is None:
        return []
    return [
        ModelCheckpoint(
            dirpath=str(ckpt_dir),
            every_n_train_steps=int(every),
            save_top_k=0,
            save_last=True,
            enable_version_counter=False,  # both callbacks write last.ckpt, not last-v1.ckpt
        )
    ]


def _trainer(
    cfg: dict[str, Any],
    root: Path | None,
    callbacks: list[Callback],
    logger: Any = False,
    train_batches: int | None = None,
    checkpoint_io: AtomicCheckpointIO | None = None,
) -> L.Trainer:
    kwargs = dict(cfg.get("trainer") or {})
    kwargs.pop("loggers", None)  # occplug's key: the loggers are built by build_loggers and passed as `logger`
    kwargs.pop(STEP_CHECKPOINT_KEY, None)  # occplug's, not a Trainer argument (see step_checkpoint)
    quiet_lightning_tips()
    if train_batches is not None:  # log at least once per epoch: no "fewer batches than the logging interval" warning
        kwargs["log_every_n_steps"] = max(1, min(int(kwargs.get("log_every_n_steps", 50)), train_batches))
    try:
        callbacks = [*callbacks, *build_callbacks(cfg)]
    except (ValueError, TypeError) as exc:
        raise RunError(str(exc).splitlines()[0]) from None
    kwargs.setdefault("enable_model_summary", False)
    notice = cpu_precision_notice(kwargs)
    if notice is not None:
        kwargs["precision"] = "32-true"
        if is_rank_zero():
            print(notice, file=sys.stderr)
    user_keys = list(kwargs)
    if root is not None:
        kwargs["default_root_dir"] = str(root)
        kwargs.setdefault("plugins", [checkpoint_io or AtomicCheckpointIO()])
    try:
        return L.Trainer(callbacks=callbacks, logger=logger, **kwargs)
    except (MisconfigurationException, ValueError, TypeError, RuntimeError) as exc:
        raise RunError(trainer_error(exc, {k: kwargs[k] for k in user_keys})) from None


#: Mixed precisions that autocast to bfloat16 on a CPU: correct there but far slower than float32 for the 3D
#: convolutions occupancy models are made of (one DuOcc step at Occ3D size took over 25 minutes instead of 5).
_CPU_SLOW_PRECISIONS = ("bf16-mixed", "bf16")


def cpu_precision_notice(trainer_kwargs: dict[str, Any]) -> str | None:
    """One ``notice:`` line when a bf16-autocast recipe lands on a machine without a GPU, else None.

    The run then trains at ``32-true`` (the caller replaces the value): a GPU recipe such as
    ``duocc/occ3d_nuscenes`` starts on a CPU at full precision instead of crawling. Only
    ``trainer.accelerator: auto`` (the default) on a machine without CUDA or MPS is changed: a user who
    names ``trainer.accelerator=cpu`` gets the precision asked for, and ``bf16-true`` (weights in bfloat16,
    no autocast) is a choice of number format, left alone.
    """
    precision = str(trainer_kwargs.get("precision", "32-true"))
    if precision not in _CPU_SLOW_PRECISIONS or str(trainer_kwargs.get("accelerator", "auto")).lower() != "auto":
        return None
    mps = getattr(torch.backends, "mps", None)
    if torch.cuda.is_available() or bool(mps is not None and mps.is_available()):
        return None
    return (
        f"notice: trainer.precision={precision} autocasts to bfloat16, which on a CPU runs 3D convolutions far "
        "slower than float32; no GPU here, so training at 32-true (trainer.accelerator=cpu keeps the recipe's precision)"
    )


#: Trainer arguments blamed, in this order, when Lightning's message names none of the set keys.
_HARDWARE_KEYS = ("accelerator", "devices", "strategy", "precision", "num_nodes")


def trainer_error(exc: BaseException, settings: dict[str, Any]) -> str:
    """Lightning's complaint about the ``trainer`` settings as one line naming the ``trainer.*`` key.

    The key is the first set argument whose name (or value) the message mentions, else the first
    set hardware argument (an accelerator this machine lacks is reported by the accelerator class).
    """
    message = " ".join(str(exc).split()) or type(exc).__name__
    lower = message.lower()
    named = [k for k in settings if k.lower() in lower]
    valued = [k for k, v in settings.items() if isinstance(v, str) and v and v.lower() in lower]
    hardware = [k for k in _HARDWARE_KEYS if k in settings]
    blamed = (named or valued or hardware or [None])[0]
    where = f"trainer.{blamed}" if blamed else "trainer"
    value = f" = {settings[blamed]!r}" if blamed else ""
    return f"{where}{value}: {message}"


#: Rank 0's run directory, for the processes a DDP launcher re-runs with the same command line
#: (their clock would name another default directory).
RUN_DIR_ENV = "OCCPLUG_RANK_ZERO_RUN_DIR"


def is_rank_zero() -> bool:
    """Whether this process is global rank 0 as far as a launcher has announced ranks
    (:func:`occplug.run.ranks.is_rank_zero`: torchrun, SLURM, Lightning's own variables)."""
    return ranks.is_rank_zero()


def default_run_dir(refs: Sequence[str]) -> Path:
    """``runs/<YYYYmmdd-HHMMSS>-<first config name>`` (in a DDP worker process: rank 0's directory)."""
    if not is_rank_zero() and os.environ.get(RUN_DIR_ENV):
        return Path(os.environ[RUN_DIR_ENV])
    stem = Path(refs[0]).stem if refs else "run"
    return Path("runs") / f"{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}-{stem}"


def fit(
    cfg: dict[str, Any],
    run_dir: Path,
    resume: bool = False,
    setup: Callable[[OccupancyModel], None] | None = None,
    callbacks: Sequence[Callback] = (),
) -> dict[str, float]:
    """Train per ``cfg`` into ``run_dir``; return the final validation metrics.

    Everything is built before anything is written, so a configuration mistake leaves no
    half-made run directory. Under a multi-process strategy (e.g. ``trainer.strategy=ddp``) every
    rank runs this function; only global rank 0 checks and writes ``run_dir``. A config with
    ``phases:`` runs through :func:`occplug.run.phases.fit_phases`, which calls this once per phase.

    Args:
        cfg: the resolved config.
        run_dir: the run directory.
        resume: continue from ``run_dir/checkpoints/last.ckpt``.
        setup: called with the built model before anything runs, after the config's ``init_from``
            (:mod:`occplug.run.weights`; not on resume): a phase loads earlier weights and freezes
            parameters here.
        callbacks: further Lightning callbacks.
    """
    if cfg.get("phases") is not None:
        raise RunError("a config with phases runs through occplug.run.phases.fit_phases (as occplug fit does)")
    run_dir = Path(run_dir)
    ckpt_dir = run_dir / "checkpoints"
    last = ckpt_dir / "last.ckpt"
    checkpoint_node = confined_checkpoint_node(cfg.get("checkpoint"))
    if resume and not last.is_file():
        raise RunError(f"--resume {run_dir}: no checkpoint at {last}")
    fresh = is_rank_zero() and not resume
    if fresh:
        check_fresh_run_dir(run_dir)
    if is_rank_zero():
        os.environ[RUN_DIR_ENV] = str(run_dir.absolute())  # inherited by the ranks a DDP launcher starts
    L.seed_everything(int(cfg.get("seed", 0)), workers=True, verbose=False)
    dm, model = build_run(cfg)
    io = AtomicCheckpointIO()
    if resume:  # the checkpoint is read (weights_only=True) and checked before anything is written
        resumed = load_checkpoint(last)
        check_resume_checkpoint(resumed, last, model.state_dict())
        io.hand_over(last, resumed)  # Lightning reads it through io: the same safe loader, not a second read
    check_trainable(model)
    if not resume:  # the top-level init_from (state-dict files); a resumed run's weights come from its checkpoint
        for line in init_from_config(model, cfg):
            if is_rank_zero():
                print(line)
    if setup is not None:
        setup(model)
    first_batch_check(model, dm)
    info = _RunInfoCallback(run_info(cfg, model, dm))
    steps = step_checkpoint(cfg, ckpt_dir)
    # no last-v1.ckpt: a resumed run (moved or copied too) rewrites its own last.ckpt
    defaults = {"save_last": True, "enable_version_counter": False}
    checkpoint = ModelCheckpoint(dirpath=str(ckpt_dir), **{**defaults, **checkpoint_node})
    guard = SignalCheckpoint(last)
    try:  # CSV (logs/version_<n>/: a resume never overwrites) and the trainer.loggers the config names
        logger = build_loggers((cfg.get("trainer") or {}).get("loggers"), run_dir)
    except UserError as exc:
        raise RunError(str(exc)) from None
    trainer = _trainer(
        cfg,
        run_dir,
        [checkpoint, *steps, info, guard, *callbacks],
        logger,
        train_batches=train_batches_per_epoch(cfg, dm),
        checkpoint_io=io,
    )
    preflight.check_run(cfg, trainer, dm, model)  # DDP / precision mistakes: one line, before anything is written
    with run_lock(run_dir) if is_rank_zero() else contextlib.nullcontext():
        if fresh:  # again under the lock: another fit may have started here meanwhile
            check_fresh_run_dir(run_dir)
        if trainer.is_global_zero:
            write_text_atomic(run_dir / "config.yaml", run_config_text(cfg))  # every component argument, defaults too
            write_text_atomic(run_dir / "plugins.json", json.dumps(plugin_versions(), indent=2) + "\n")
            write_text_atomic(run_dir / "environment.json", json.dumps(numeric_environment(), indent=2) + "\n")
        with interruptible(guard), data_errors(), warnings.catch_warnings():
            # the train loader does resume mid-epoch (OccDataModule.state_dict), through a path Lightning does not see
            warnings.filterwarnings("ignore", message=".*your dataloader is not resumable")
            trainer.fit(model, datamodule=dm, ckpt_path=str(last) if resume else None)
            if info.last_saved_step != trainer.global_step:  # the final steps came after the last checkpoint
                trainer.save_checkpoint(str(last))
            if info.last_val_step != trainer.global_step:  # training stopped between validations
                trainer.validate(model, datamodule=dm, verbose=False)
        results = dict(model.last_results.get("val", {}))
        if trainer.is_global_zero:
            masks = info.info["masks"]
            batch = model.effective_batch
            payload = {
                **results,
                "global_step": trainer.global_step,
                "epoch": trainer.current_epoch,
                **masks,
                "effective_batch": None if batch is None else batch.total,
                "effective_batch_parts": None
                if batch is None
                else {"devices": batch.devices, "per_device": batch.per_device, "accumulation": batch.accumulation},
                "lr": model.effective_lr,
                **dm.label_cut.describe(),
            }
            write_json(run_dir / "metrics.json", payload)
            print_tables(model.last_tables, masks)
    return results


def write_json(path: Path, payload: dict[str, Any]) -> None:
    """Write strict JSON (NaN, e.g. the IoU of a class absent from both sides, becomes ``null``)."""

    def clean(v: Any) -> Any:
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, list):
            return [clean(x) for x in v]
        return v

    write_text_atomic(Path(path), json.dumps(clean(payload), indent=2, allow_nan=False) + "\n")


def print_tables(tables: dict[str, str], masks: dict[str, Any]) -> None:
    """Print every metric's per-class table under one line naming the masks."""
    shown = [t for t in tables.values() if t]
    if shown:
        print(describe_masks(masks))
        for table in shown:
            print(table)


@contextlib.contextmanager
def data_errors() -> Iterator[None]:
    """A bad data file met during a loop (possibly in a loader worker) becomes one :class:`RunError` line."""
    try:
        yield
    except FormatError as exc:
        raise RunError(_original_message(exc)) from None
    except UserError as exc:
        raise RunError(_first_line(exc)) from None
    except Exception as exc:
        # DataLoader workers re-raise the worker's exception type with the worker traceback in the message
        if type(exc).__name__ == "FormatError" or "FormatError: " in str(exc):
            raise RunError(_original_message(exc)) from None
        raise


def _original_message(exc: BaseException) -> str:
    text = str(exc).strip()
    marker = "FormatError: "
    if marker in text:  # "Caught FormatError in DataLoader worker ... Original Traceback ... FormatError: <msg>"
        return text.rsplit(marker, 1)[1].splitlines()[0]
    return text.splitlines()[0] if text else type(exc).__name__


def checkpoint_info(ckpt: dict[str, Any], path: Path) -> dict[str, Any]:
    """The :func:`run_info` an occplug checkpoint carries."""
    info = ckpt.get(CHECKPOINT_KEY)
    if not isinstance(info, dict) or "config" not in info:
        raise RunError(f"checkpoint {path} carries no occplug config; pass -c CONFIG")
    return info


def config_from_checkpoint(ckpt: dict[str, Any], path: Path) -> dict[str, Any]:
    """The resolved config stored in an occplug checkpoint."""
    return checkpoint_info(ckpt, path)["config"]


def check_checkpoint_plugins(info: dict[str, Any], path: Path) -> None:
    """Raise one line naming the first plugin a checkpoint's components need that is not installed."""
    registry = get_registry()
    for comp in info.get("components") or []:
        if not registry.has(comp["kind"], comp["type"]):
            dist = comp.get("distribution") or comp["plugin"]
            version = comp.get("version") or (info.get("plugins") or {}).get(comp["plugin"])
            raise RunError(
                f"checkpoint {path} needs plugin '{comp['plugin']}' ({dist}{' ' + version if version else ''}) for "
                f"{comp['path']}: {comp['kind']} '{comp['type']}', which is not installed; pip install {dist}"
                f"{'==' + version if version else ''}"
            )


def build_run(cfg: dict[str, Any]) -> tuple[OccDataModule, OccupancyModel]:
    """Data module and model, the data module told which optional fields the model reads.

    A component rejecting its arguments, or a data file the model needs being missing, is a
    user-facing error.
    """
    try:
        dm = build_datamodule(cfg)
        model = build_model(cfg, dm)
        check_streaming(model, dm)  # a stateful component needs data.sequential
        dm.require_fields(set(model.required_fields()) | callback_requirements(cfg))
        return dm, model
    except FormatError as exc:
        raise RunError(str(exc).splitlines()[0]) from None
    except (ValueError, TypeError, FileNotFoundError, ImportError) as exc:
        raise RunError(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None


def train_batches_per_epoch(cfg: dict[str, Any], dm: OccDataModule) -> int:
    """Training batches one process runs per epoch (after ``trainer.limit_train_batches``)."""
    trainer = cfg.get("trainer") or {}
    devices = trainer.get("devices", 1)
    world = devices if isinstance(devices, int) and devices > 0 else 1
    batches = math.ceil(len(dm.dataset("train")) / max(1, int(dm.batch_size) * world))  # type: ignore[arg-type]
    limit = trainer.get("limit_train_batches")
    if isinstance(limit, int) and not isinstance(limit, bool):
        batches = min(batches, limit)
    elif isinstance(limit, float):
        batches = max(1, int(batches * limit))
    return max(1, batches)


def check_trainable(model: OccupancyModel) -> None:
    """Refuse to fit a model that would learn nothing: no supervision, or every weight <= 0."""
    weights = model.loss_weights()
    if not weights:
        raise RunError(
            "model.supervision: the model has no supervision source, so fit would train nothing; "
            "add one (e.g. model.supervision.voxel_labels={type: voxel_ce})"
        )
    if all(w <= 0 for w in weights.values()):
        shown = ", ".join(f"{name}: {w:g}" for name, w in weights.items())
        raise RunError(f"model.supervision: every loss weight is <= 0 ({shown}), so fit would train nothing")


def first_batch_check(model: OccupancyModel, dm: OccDataModule) -> None:
    """Run one training batch through a copy of the model before anything is written.

    A component's :class:`~occplug.errors.UserError` (or ``ValueError``) on real data -- an image
    size its stride does not divide, a label grid that does not fit -- then costs seconds and leaves
    no run directory. The check changes nothing about the run: it works on a deep copy (BatchNorm
    statistics, stream state), reads the dataset directly (not the trainer's loader) and restores
    every random-number generator afterwards.
    """
    import copy
    import random

    dataset = dm.dataset("train")
    count = min(int(dm.batch_size), len(dataset))  # type: ignore[arg-type]
    if count == 0:
        raise RunError("data: the training split is empty")
    py_state, np_state = random.getstate(), np.random.get_state()
    try:
        with torch.random.fork_rng(devices=[]), torch.no_grad(), data_errors():
            batch = dm.collate([dataset[i] for i in range(count)])
            probe = copy.deepcopy(model)
            probe.train()
            probe.dry_run(batch)
    except ValueError as exc:  # UserError, and the ValueErrors components raised before it existed
        raise RunError(_first_line(exc)) from None
    finally:
        random.setstate(py_state)
        np.random.set_state(np_state)


def _first_line(exc: BaseException) -> str:
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__


def callback_requirements(cfg: dict[str, Any]) -> set[str]:
    """Frame fields the configured callbacks declare in ``requires``."""
    out: set[str] = set()
    for node in (cfg.get("callbacks") or {}).values():
        if node is not None:
            out |= set(getattr(get_registry().get("callback", node["type"]).factory, "requires", ()))
    return out


def restore_run(cfg: dict[str, Any], ckpt: dict[str, Any], path: Path) -> tuple[OccDataModule, OccupancyModel]:
    """The data module and model of a run's ``cfg`` with the checkpoint ``ckpt`` (read from ``path``) loaded."""
    dm, model = build_run(cfg)
    try:
        model.load_state_dict(ckpt["state_dict"])
    except (KeyError, RuntimeError) as exc:
        raise RunError(f"checkpoint {path} does not match the configured model: {str(exc).splitlines()[0]}") from None
    return dm, model


@dataclass
class Evaluation:
    """What :func:`evaluate` found: flat metrics, per-metric tables and the mask settings."""

    results: dict[str, float]
    tables: dict[str, str]
    masks: dict[str, Any]


def evaluate(cfg: dict[str, Any], ckpt_path: Path, stage: str = "validate") -> Evaluation:
    """Evaluate a checkpoint on the ``validate`` or ``test`` split."""
    ckpt = load_checkpoint(ckpt_path)
    dm, model = restore_run(cfg, ckpt, ckpt_path)
    trainer = _trainer(cfg, None, [])
    preflight.check_run(cfg, trainer, dm, splits=("val" if stage == "validate" else "test",))
    with data_errors():
        if stage == "validate":
            trainer.validate(model, datamodule=dm, verbose=False)
        else:
            trainer.test(model, datamodule=dm, verbose=False)
    key = "val" if stage == "validate" else "test"
    return Evaluation(dict(model.last_results.get(key, {})), dict(model.last_tables), mask_settings(cfg, model))


def predict(cfg: dict[str, Any], ckpt_path: Path, out: Path) -> int:
    """Write ``<out>/<token>.npz`` (key ``pred``: ``(X, Y, Z)`` uint8 class ids) per sample; return the count."""
    ckpt = load_checkpoint(ckpt_path)
    dm, model = restore_run(cfg, ckpt, ckpt_path)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    trainer = _trainer(cfg, None, [_NpzPredictionWriter(out)])
    with data_errors():
        trainer.predict(model, datamodule=dm, return_predictions=False)
    return len(list(out.glob("*.npz")))


def resolve_run_config(refs: Sequence[str], overrides: Sequence[str], ckpt: Path | None = None) -> dict[str, Any]:
    """Config for validate/test/predict: the checkpoint's own config, with ``-c`` files and overrides on top.

    Without a checkpoint config, ``-c`` is required. A checkpoint whose components come from a
    plugin that is not installed fails naming that plugin and its version.
    """
    saved = None
    if ckpt is not None:
        data = load_checkpoint(ckpt)
        if refs and not isinstance(data.get(CHECKPOINT_KEY), dict):
            return load_config(refs, overrides)  # a foreign checkpoint: -c carries the whole config
        info = checkpoint_info(data, ckpt)
        check_checkpoint_plugins(info, ckpt)
        saved = info["config"]
    if saved is None and not refs:
        raise ConfigError("no -c CONFIG given")
    return load_config(refs, overrides, saved=saved)
