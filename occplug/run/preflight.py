"""Distributed and precision settings checked before a run writes anything (``occplug fit / validate / test``).

Lightning finds some hardware mistakes when the Trainer is built (a GPU count this machine lacks); others it
finds only once the processes run -- after the run directory is made, on every rank, as a traceback. This module
checks those on the built Trainer, data module and model, before anything is written:

* a sequential (stream-ordered) evaluation split with fewer scenes than ranks;
* ``trainer.sync_batchnorm`` with several CPU processes (``SyncBatchNorm`` runs on GPUs only);
* ``trainer.precision`` ``16-mixed`` on a CPU (Lightning would switch it to bf16 silently), bf16 on a GPU
  without bfloat16;
* more CPU processes than the machine has cores;
* ``trainer.num_nodes > 1`` with no launcher telling this node its rank and where rank 0 listens;
* ``optimizer.param_groups`` whose prefix matches no parameter of the built model.

Each is one line naming the ``trainer.*`` (or ``data.*`` / ``optimizer.*``) key; :func:`check_run` raises the
first as :class:`~occplug.run.checkpoints.RunError`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

from occplug.errors import ConfigError
from occplug.run.checkpoints import RunError

__all__ = ["RunPlan", "check_plan", "check_run", "check_sequential_eval", "plan_of"]


@dataclass(frozen=True)
class RunPlan:
    """What a Trainer will do: ``accelerator`` (``cpu``, ``cuda``, ``mps``, ...), processes per node
    (``devices``), ``num_nodes``, the ``precision`` the config asked for, ``sync_batchnorm``, and the launcher
    that started this process (:func:`occplug.run.ranks.launcher_rank`)."""

    accelerator: str
    devices: int
    num_nodes: int = 1
    precision: str = "32-true"
    sync_batchnorm: bool = False
    launcher: str = "none"

    @property
    def world_size(self) -> int:
        return self.devices * self.num_nodes

    def describe(self) -> str:
        return f"trainer.devices={self.devices} x trainer.num_nodes={self.num_nodes}: {self.world_size} ranks"


def _accelerator_name(accelerator: Any) -> str:
    name = type(accelerator).__name__.lower()
    return name[: -len("accelerator")] if name.endswith("accelerator") else name


def plan_of(trainer: Any, cfg: dict[str, Any]) -> RunPlan:
    """The :class:`RunPlan` of a built ``lightning.Trainer`` and the config it was built from."""
    from occplug.run.ranks import launcher_rank

    settings = cfg.get("trainer") or {}
    return RunPlan(
        accelerator=_accelerator_name(trainer.accelerator),
        devices=int(trainer.num_devices),
        num_nodes=int(trainer.num_nodes),
        precision=str(settings.get("precision", trainer.precision)),
        sync_batchnorm=bool(settings.get("sync_batchnorm", False)),
        launcher=launcher_rank().launcher,
    )


def _bf16_supported() -> bool:
    import torch

    return bool(torch.cuda.is_available() and torch.cuda.is_bf16_supported())


def check_plan(plan: RunPlan, env: dict[str, str] | None = None, cpu_count: int | None = None) -> str | None:
    """The first hardware / precision / launcher problem of ``plan`` as one line, else None.

    ``env`` (default ``os.environ``) and ``cpu_count`` (default ``os.cpu_count()``) are what the machine offers.
    """
    env = dict(os.environ) if env is None else env
    cpus = (os.cpu_count() or 1) if cpu_count is None else cpu_count
    precision = plan.precision
    if plan.sync_batchnorm and plan.accelerator == "cpu" and plan.world_size > 1:
        return (
            f"trainer.sync_batchnorm = True: SyncBatchNorm synchronises over GPUs only, and this run is "
            f"{plan.world_size} CPU processes; set trainer.sync_batchnorm=false (or train on GPUs)"
        )
    if plan.accelerator == "cpu" and precision in ("16-mixed", "16", "16-true"):
        return (
            f"trainer.precision = {precision!r}: float16 is not supported on a CPU (Lightning would switch to "
            "bf16-mixed); use 32-true or bf16-mixed"
        )
    if plan.accelerator == "cuda" and precision.startswith("bf16") and not _bf16_supported():
        return (
            f"trainer.precision = {precision!r}: this GPU has no bfloat16 support (torch.cuda.is_bf16_supported() "
            "is False); use 16-mixed or 32-true"
        )
    if plan.accelerator == "cpu" and plan.devices > cpus:
        return (
            f"trainer.devices = {plan.devices}: this machine has {cpus} CPU core(s) and each CPU device is a "
            f"process; use at most trainer.devices={cpus}"
        )
    if plan.num_nodes > 1 and plan.launcher in ("none", "lightning"):
        missing = [k for k in ("MASTER_ADDR", "MASTER_PORT") if k not in env]
        if not any(k in env for k in ("NODE_RANK", "GROUP_RANK")):
            missing.insert(0, "NODE_RANK")
        if missing:
            return (
                f"trainer.num_nodes = {plan.num_nodes}: no launcher told this node its rank and where rank 0 "
                f"listens ({', '.join(missing)} not set); start one command per node with NODE_RANK, MASTER_ADDR "
                "and MASTER_PORT set, or with torchrun / srun (README: Multi-node training)"
            )
    return None


class _StandIn:
    """The two attributes a data module's ``sampler`` reads from its trainer."""

    def __init__(self, world_size: int) -> None:
        self.world_size = world_size
        self.global_rank = 0


def check_sequential_eval(dm: Any, split: str, world_size: int) -> str | None:
    """Build ``split``'s sampler as rank 0 of ``world_size`` would; its complaint (a sequential evaluation
    split with fewer scenes than ranks) as one line, else None."""
    if world_size < 2:
        return None
    dataset = dm.dataset(split)
    saved = getattr(dm, "trainer", None)
    dm.trainer = _StandIn(world_size)
    try:
        dm.sampler(split, dataset)
    except ValueError as exc:
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        return f"data ({split} split): {message}; use at most that many ranks, or more {split} scenes"
    finally:
        dm.trainer = saved
    return None


def check_run(
    cfg: dict[str, Any], trainer: Any, dm: Any, model: Any = None, splits: tuple[str, ...] = ("val",)
) -> None:
    """Raise :class:`RunError` with the first problem of the module docstring's list, before anything is written.

    ``splits`` are the evaluation splits the run reads (``fit``: ``val``); ``model``, when given, is checked
    against ``optimizer.param_groups``.
    """
    plan = plan_of(trainer, cfg)
    problem = check_plan(plan)
    for split in splits:
        if problem is None:
            sequential = check_sequential_eval(dm, split, plan.world_size)
            problem = sequential and f"{plan.describe()}; {sequential}"
    if problem is None and model is not None and cfg.get("optimizer") is not None:
        from occplug.optim import parameter_groups

        try:
            parameter_groups(model, cfg["optimizer"], 1.0)
        except ConfigError as exc:
            problem = str(exc)
    if problem is not None:
        raise RunError(problem)
