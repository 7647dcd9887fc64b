"""Rank 0 from the launcher's variables (torchrun, SLURM, Lightning's own), and two local processes as two nodes."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from occplug.run import ranks

ROOT = Path(__file__).resolve().parents[2]
BASELINE = str(ROOT / "configs" / "baseline.yaml")

#: Every variable a launcher may set that the rank logic reads.
LAUNCHER_VARIABLES = (
    "RANK", "LOCAL_RANK", "NODE_RANK", "GROUP_RANK", "WORLD_SIZE", "TORCHELASTIC_RUN_ID", "SLURM_NTASKS",
    "SLURM_NTASKS_PER_NODE", "SLURM_PROCID", "SLURM_NODEID", "SLURM_LOCALID", "SLURM_JOB_NAME", "LSB_JOBID", "LSB_DJOB_RANKFILE",
    "JSM_NAMESPACE_LOCAL_RANK", "JSM_NAMESPACE_SIZE", "JSM_NAMESPACE_RANK",
)  # fmt: skip

TORCHRUN = {"TORCHELASTIC_RUN_ID": "abc", "WORLD_SIZE": "8"}
SLURM = {"SLURM_NTASKS": "8", "SLURM_NTASKS_PER_NODE": "4", "SLURM_JOB_NAME": "train"}


@pytest.mark.parametrize(
    ("env", "launcher", "zero"),
    [
        pytest.param({}, "none", True, id="no launcher"),
        # Lightning's own environment: one command per node with NODE_RANK (the first process of node 1 has no
        # LOCAL_RANK yet; it used to take itself for rank 0), and the processes Lightning's launcher starts.
        pytest.param({"NODE_RANK": "1"}, "lightning", False, id="node 1, its first process"),
        pytest.param({"GROUP_RANK": "1"}, "lightning", False, id="group rank 1"),
        pytest.param({"NODE_RANK": "0"}, "lightning", True, id="node 0, its first process"),
        pytest.param({"NODE_RANK": "0", "LOCAL_RANK": "1"}, "lightning", False, id="node 0, process 1"),
        pytest.param({"NODE_RANK": "1", "LOCAL_RANK": "0"}, "lightning", False, id="node 1, process 0"),
        pytest.param({"RANK": "2", "LOCAL_RANK": "0"}, "lightning", False, id="a global RANK alone"),
        # torchrun: RANK is the global rank (GROUP_RANK the node)
        pytest.param({**TORCHRUN, "RANK": "0", "GROUP_RANK": "0", "LOCAL_RANK": "0"}, "torchrun", True, id="torchrun 0"),
        pytest.param({**TORCHRUN, "RANK": "4", "GROUP_RANK": "1", "LOCAL_RANK": "0"}, "torchrun", False, id="torchrun 4"),
        # srun: SLURM_PROCID is the global rank; torchrun inside srun wins, as in Lightning
        pytest.param({**SLURM, "SLURM_PROCID": "0", "SLURM_NODEID": "0", "SLURM_LOCALID": "0"}, "slurm", True,
                     id="srun task 0"),
        pytest.param({**SLURM, "SLURM_PROCID": "5", "SLURM_NODEID": "1", "SLURM_LOCALID": "1"}, "slurm", False,
                     id="srun task 5"),
        pytest.param({**SLURM, **TORCHRUN, "SLURM_PROCID": "1", "RANK": "4", "GROUP_RANK": "1"}, "torchrun", False,
                     id="torchrun in srun"),
        # an interactive allocation (job name bash): Lightning ignores SLURM, and so does the rank
        pytest.param({"SLURM_NTASKS": "1", "SLURM_JOB_NAME": "bash", "SLURM_PROCID": "3"}, "none", True,
                     id="interactive salloc"),
        pytest.param({"LOCAL_RANK": "0", "NODE_RANK": "0", "SLURM_PROCID": "3"}, "lightning", True,
                     id="SLURM_PROCID without srun"),
    ],
)  # fmt: skip
def test_the_rank_is_the_launchers(monkeypatch, env, launcher, zero):
    for key in LAUNCHER_VARIABLES:
        monkeypatch.delenv(key, raising=False)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    found = ranks.launcher_rank()
    assert (found.launcher, found.is_zero, ranks.is_rank_zero()) == (launcher, zero, zero)
    from lightning.fabric.plugins.environments import SLURMEnvironment, TorchElasticEnvironment

    if launcher == "torchrun":  # the global rank is the one Lightning's environment will use
        assert found.rank == TorchElasticEnvironment().global_rank()
    if launcher == "slurm":
        assert found.rank == SLURMEnvironment().global_rank()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_local_processes_as_two_nodes_train_into_one_run_directory(tmp_path):
    """``trainer.num_nodes=2``, one ``occplug fit`` per node (gloo, CPU); node 1 starts after node 0 has written
    the run directory, as a second machine does, and must neither refuse it nor write to it."""
    run = tmp_path / "run"
    cmd = [
        sys.executable, "-m", "occplug.cli", "fit", "-c", BASELINE, "-c", "occplug/trainer/debug", "--run-dir",
        str(run), "data.preset=tiny", "data.frames_per_scene=2", "data.train_scenes=1", "data.val_scenes=1",
        "data.test_scenes=0", "data.batch_size=1", "trainer.accelerator=cpu", "trainer.devices=1",
        "trainer.num_nodes=2", "trainer.strategy=ddp",
    ]  # fmt: skip
    base = {k: v for k, v in os.environ.items() if k not in LAUNCHER_VARIABLES}
    env = {**base, "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(_free_port()), "PYTHONWARNINGS": "ignore"}
    env["OMP_NUM_THREADS"] = "1"
    logs = [open(tmp_path / f"node{i}.log", "w") for i in range(2)]  # noqa: SIM115
    nodes = [subprocess.Popen(cmd, env={**env, "NODE_RANK": "0"}, stdout=logs[0], stderr=subprocess.STDOUT)]
    try:
        deadline = time.monotonic() + 240
        while not (run / "config.yaml").is_file():  # node 0 is waiting at the rendezvous now
            assert nodes[0].poll() is None, (tmp_path / "node0.log").read_text()[-3000:]
            assert time.monotonic() < deadline, "node 0 wrote no run directory"
            time.sleep(0.5)
        nodes.append(subprocess.Popen(cmd, env={**env, "NODE_RANK": "1"}, stdout=logs[1], stderr=subprocess.STDOUT))
        codes = [p.wait(timeout=300) for p in reversed(nodes)]
    finally:
        for p in nodes:
            if p.poll() is None:
                p.kill()
                p.wait()
        for log in logs:
            log.close()
    text = [(tmp_path / f"node{i}.log").read_text() for i in range(2)]
    assert codes == [0, 0], text[1][-3000:] + "\n---\n" + text[0][-3000:]
    assert sorted(p.name for p in run.iterdir()) == [
        "checkpoints",
        "config.yaml",
        "environment.json",
        "logs",
        "metrics.json",
        "plugins.json",
    ]
    assert [p.name for p in (run / "logs").iterdir()] == ["version_0"]
    metrics = json.loads((run / "metrics.json").read_text())
    # the 2 training frames shared by the 2 ranks: one step of effective batch 2 (debug: one epoch)
    assert metrics["global_step"] == 1 and metrics["effective_batch"] == 2
    assert metrics["effective_batch_parts"]["devices"] == 2
    assert "run directory:" in text[0] and "run directory:" not in text[1]  # only rank 0 reports
