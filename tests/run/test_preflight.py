"""DDP and precision mistakes found before anything is written: one ``error:`` line, exit 2, no run directory."""

from __future__ import annotations

from pathlib import Path

import pytest

from occplug.cli import main
from occplug.run import preflight
from occplug.run.preflight import RunPlan, check_plan

ROOT = Path(__file__).resolve().parents[2]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
TINY = ["data.preset=tiny", "trainer.enable_progress_bar=false", "trainer.max_steps=2", "trainer.limit_val_batches=1"]
LAUNCHED = {"NODE_RANK": "0", "MASTER_ADDR": "10.0.0.1", "MASTER_PORT": "29500"}


@pytest.mark.parametrize(
    ("plan", "env", "line"),
    [
        (RunPlan("cpu", 2, sync_batchnorm=True), {}, "trainer.sync_batchnorm = True: SyncBatchNorm synchronises over GPUs"),
        (RunPlan("cpu", 1, num_nodes=2, sync_batchnorm=True), LAUNCHED, "trainer.sync_batchnorm = True"),
        (RunPlan("cpu", 1, precision="16-mixed"), {}, "trainer.precision = '16-mixed': float16 is not supported on a CPU"),
        (RunPlan("cpu", 5), {}, "trainer.devices = 5: this machine has 4 CPU core(s)"),
        (RunPlan("cpu", 1, num_nodes=2), {}, "trainer.num_nodes = 2: no launcher told this node its rank and where "
                                             "rank 0 listens (NODE_RANK, MASTER_ADDR, MASTER_PORT not set)"),
        (RunPlan("cpu", 1, num_nodes=2, launcher="lightning"), {"NODE_RANK": "1"},
         "trainer.num_nodes = 2: no launcher told this node its rank and where rank 0 listens (MASTER_ADDR, MASTER_PORT"),
    ],
)  # fmt: skip
def test_each_misconfiguration_is_one_line(plan, env, line):
    found = check_plan(plan, env=env, cpu_count=4)
    assert found is not None and found.startswith(line) and "\n" not in found, found


@pytest.mark.parametrize(
    ("plan", "env"),
    [
        (RunPlan("cpu", 1, sync_batchnorm=True), {}),  # one process: nothing to synchronise, harmless
        (RunPlan("cpu", 4, precision="bf16-mixed"), {}),
        (RunPlan("cpu", 1, num_nodes=2, launcher="lightning"), LAUNCHED),
        (RunPlan("cuda", 8, num_nodes=4, launcher="torchrun", sync_batchnorm=True), {}),  # torchrun: its own rendezvous
        (RunPlan("cuda", 8, num_nodes=2, launcher="slurm", precision="16-mixed"), {}),
    ],
)
def test_sound_plans_pass(plan, env, monkeypatch):
    monkeypatch.setattr(preflight, "_bf16_supported", lambda: True)
    assert check_plan(plan, env=env, cpu_count=4) is None


def test_bf16_on_a_gpu_without_it(monkeypatch):
    monkeypatch.setattr(preflight, "_bf16_supported", lambda: False)
    found = check_plan(RunPlan("cuda", 1, precision="bf16-mixed"), env={}, cpu_count=4)
    assert found == (
        "trainer.precision = 'bf16-mixed': this GPU has no bfloat16 support (torch.cuda.is_bf16_supported() is False); "
        "use 16-mixed or 32-true"
    )


def fit_fails(tmp_path, capsys, config: str, *overrides: str) -> str:
    run_dir = tmp_path / "run"
    code = main(["fit", "-c", config, *TINY, *overrides, "--run-dir", str(run_dir)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert not run_dir.exists(), "a failed check must leave no run directory"
    errors = [line for line in err if line.startswith("error: ")]
    assert len(errors) == 1 and "Traceback" not in "\n".join(err), err
    return errors[0]


DDP2 = ["trainer.accelerator=cpu", "trainer.devices=2", "trainer.strategy=ddp"]


def test_sequential_evaluation_with_fewer_scenes_than_ranks(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("os.cpu_count", lambda: 4)  # the check is not about this machine's cores
    small = ["grid.range=[-8.0,-8.0,-1.0,8.0,8.0,5.4]", "model.encoder.out_channels=16", "model.encoder.width=16"]
    line = fit_fails(
        tmp_path, capsys, "duocc/stream_agg_concat", *small, *DDP2, "data.val_scenes=1", "data.train_scenes=1"
    )
    assert line == (
        "error: trainer.devices=2 x trainer.num_nodes=1: 2 ranks; data (val split): sequential evaluation needs a "
        "scene per rank: 1 scene(s) for 2 ranks; use at most that many ranks, or more val scenes"
    )


@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        (["trainer.sync_batchnorm=true"], "error: trainer.sync_batchnorm = True: SyncBatchNorm synchronises over GPUs"),
        (["trainer.devices=1", "trainer.precision=16-mixed"], "error: trainer.precision = '16-mixed': float16"),
        (["trainer.devices=1", "trainer.num_nodes=2"], "error: trainer.num_nodes = 2: no launcher told this node"),
        (["trainer.devices=64"], "error: trainer.devices = 64: this machine has"),
    ],
)
def test_fit_stops_before_writing(tmp_path, capsys, monkeypatch, overrides, expected):
    for key in ("NODE_RANK", "GROUP_RANK", "LOCAL_RANK", "RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setattr("os.cpu_count", lambda: 4)
    assert fit_fails(tmp_path, capsys, BASELINE, *DDP2, *overrides).startswith(expected)


def test_a_phased_run_stops_before_its_run_directory(tmp_path, capsys, monkeypatch):
    """configs/semi/baseline_10pct.yaml (teacher, student with teacher pseudo labels, finetune): its last phase on
    2 CPU processes with SyncBatchNorm is found before the teacher trains."""
    monkeypatch.setattr("os.cpu_count", lambda: 4)
    semi = str(ROOT / "configs" / "semi" / "baseline_10pct.yaml")
    line = fit_fails(tmp_path, capsys, semi, *DDP2, "phases.finetune.trainer.sync_batchnorm=true")
    assert line.startswith("error: phases.finetune: trainer.sync_batchnorm = True: SyncBatchNorm synchronises over")
