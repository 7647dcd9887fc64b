"""Which process is global rank 0, read from the launcher's variables before any process group exists.

``occplug fit`` decides who checks and writes the run directory before Lightning starts the process group, so
it reads the rank where the launcher put it, in the order Lightning picks its cluster environment
(``lightning.fabric.plugins.environments``): torchrun / TorchElastic (``RANK``), SLURM's ``srun``
(``SLURM_PROCID``), LSF's ``jsrun``, MPI; else Lightning's own environment, where the node is ``NODE_RANK``
(or ``GROUP_RANK``) and the process on it ``LOCAL_RANK`` (Lightning's DDP launcher sets both in the processes
it starts; a user starting one command per node sets ``NODE_RANK``). A process is rank 0 only when every rank
it was given is 0, so the first process of a second node never takes itself for rank 0.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass

__all__ = ["LauncherRank", "is_rank_zero", "launcher_rank"]

#: Variables that announce a rank in Lightning's own environment (and launchers it does not know by name).
_RANK_VARIABLES = ("RANK", "NODE_RANK", "GROUP_RANK", "LOCAL_RANK")


@dataclass(frozen=True)
class LauncherRank:
    """What the launcher announced: ``launcher`` (``torchrun``, ``slurm``, ``lsf``, ``mpi``, ``lightning``,
    ``none``) and the global ``rank`` (None where only node and local ranks are known)."""

    launcher: str
    rank: int | None
    node_rank: int = 0
    local_rank: int = 0

    @property
    def is_zero(self) -> bool:
        return (self.rank or 0) == 0 and self.node_rank == 0 and self.local_rank == 0


def _int(env: os._Environ[str], key: str) -> int:
    try:
        return int(env.get(key) or 0)
    except ValueError:
        return 0


def launcher_rank() -> LauncherRank:
    """This process's rank as its launcher announced it in ``os.environ``."""
    from lightning.fabric.plugins.environments import (
        LSFEnvironment,
        MPIEnvironment,
        SLURMEnvironment,
        TorchElasticEnvironment,
    )

    env = os.environ
    with warnings.catch_warnings():  # SLURM's "srun is available but not used" hint: Lightning gives it itself
        warnings.simplefilter("ignore")
        if TorchElasticEnvironment.detect():
            return LauncherRank("torchrun", _int(env, "RANK"), _int(env, "GROUP_RANK"), _int(env, "LOCAL_RANK"))
        if SLURMEnvironment.detect():
            return LauncherRank(
                "slurm", _int(env, "SLURM_PROCID"), _int(env, "SLURM_NODEID"), _int(env, "SLURM_LOCALID")
            )
        if LSFEnvironment.detect():
            return LauncherRank("lsf", LSFEnvironment().global_rank(), 0, _int(env, "JSM_NAMESPACE_LOCAL_RANK"))
        if MPIEnvironment.detect():
            return LauncherRank("mpi", MPIEnvironment().global_rank())
    if not any(key in env for key in _RANK_VARIABLES):
        return LauncherRank("none", 0)
    node = _int(env, "NODE_RANK") if "NODE_RANK" in env else _int(env, "GROUP_RANK")
    return LauncherRank("lightning", _int(env, "RANK") if "RANK" in env else None, node, _int(env, "LOCAL_RANK"))


def is_rank_zero() -> bool:
    """Whether this process is global rank 0 (see the module docstring); a process no launcher started is."""
    return launcher_rank().is_zero
