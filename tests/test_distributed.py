"""Distributed training: `occplug fit ... trainer.devices=2 trainer.strategy=ddp` as a user types it.

Two gloo processes (Lightning's ``ddp`` strategy re-launches the ``occplug`` console script) train
the baseline on a small synthetic world with an odd number of samples, so that the ranks get
uneven shares; the run's final validation (after ``fit``, as the last epoch ran none) must
equal a single-process ``occplug validate`` of the checkpoint it wrote.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from occplug.cli import main
from occplug.data.datamodule import EvalShardSampler

ROOT = Path(__file__).resolve().parents[1]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
# 3 training and 3 validation samples, batch 1: rank 0 validates samples 0 and 2, rank 1 sample 1.
DATA = ["data.preset=tiny", "data.frames_per_scene=3", "data.train_scenes=1", "data.test_scenes=0", "data.batch_size=1"]
# Validation runs inside fit after epoch 2 (uneven batches through the DDP-wrapped model), and
# again after fit (epoch 3 ended without one): the runner's final trainer.validate.
RUN = [
    "trainer.accelerator=cpu",
    "trainer.enable_progress_bar=false",
    "trainer.max_epochs=3",
    "trainer.check_val_every_n_epoch=2",
    "trainer.log_every_n_steps=1",
]


def occplug_command() -> list[str]:
    """The installed ``occplug`` console script (what a user runs), else ``python -m occplug.cli``."""
    script = Path(sys.executable).with_name("occplug")
    if script.is_file():
        return [str(script)]
    found = shutil.which("occplug")
    return [found] if found else [sys.executable, "-m", "occplug.cli"]


def same(a: float | None, b: float | None) -> bool:
    """Equal values, or both undefined (``null`` in metrics.json: a class absent from truth and prediction)."""
    return a == b


def test_eval_shard_sampler_splits_every_sample_exactly_once() -> None:
    data = list(range(7))
    shares = [list(EvalShardSampler(data, 3, r)) for r in range(3)]
    assert shares == [[0, 3, 6], [1, 4], [2, 5]]
    assert [len(EvalShardSampler(data, 3, r)) for r in range(3)] == [3, 2, 2]
    assert EvalShardSampler.for_current_process(data) is None  # no process group here


def test_ddp_fit_on_two_processes_equals_single_process_validation(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    cmd = [*occplug_command(), "fit", "-c", BASELINE, *DATA, *RUN, "trainer.devices=2", "trainer.strategy=ddp"]
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]

    # One run directory (rank 1 re-ran the command a moment later: same default name), written once.
    runs = list((tmp_path / "runs").iterdir())
    assert len(runs) == 1, runs
    run = runs[0]
    assert sorted(p.name for p in run.iterdir()) == [
        "checkpoints",
        "config.yaml",
        "environment.json",
        "logs",
        "metrics.json",
        "plugins.json",
    ]
    assert [p.name for p in (run / "logs").iterdir()] == ["version_0"]
    assert (run / "checkpoints" / "last.ckpt").is_file()
    assert proc.stdout.count("run directory:") == 1 and proc.stdout.count("metrics:") == 1

    ddp = json.loads((run / "metrics.json").read_text())
    # Each rank trained on its half of the 3 samples (padded to 2 each): 2 steps an epoch, where one process takes 3.
    assert ddp["global_step"] == 6 and ddp["epoch"] == 3
    logged = (run / "logs" / "version_0" / "metrics.csv").read_text().splitlines()
    header = logged[0].split(",")
    val_steps = [row.split(",")[header.index("step")] for row in logged[1:] if row.split(",")[header.index("val/IoU")]]
    assert val_steps == ["3", "6"], "one validation inside fit (after epoch 2), one after it (step 6)"

    out = tmp_path / "single.json"
    torch_threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as in each DDP worker (Lightning gives each process cores / processes)
    try:
        code = main(
            [
                "validate",
                "--ckpt",
                str(run / "checkpoints" / "last.ckpt"),
                "--json",
                str(out),
                "trainer.devices=1",
                "trainer.strategy=auto",
            ]
        )
    finally:
        torch.set_num_threads(torch_threads)
    assert code == 0
    single = json.loads(out.read_text())
    assert math.isfinite(single["mIoU"]) and math.isfinite(single["IoU"]) and single["IoU"] > 0
    assert ddp["effective_batch"] == 2 and ddp["effective_batch_parts"]["devices"] == 2  # 2 processes x 1 sample
    assert ddp["eval_mask"] == single["eval_mask"] == "camera"
    keys = [k for k in single if k == "mIoU" or k.startswith("IoU")]
    assert len(keys) == 19  # mIoU, geometric IoU, 17 classes
    mismatched = {k: (ddp[k], single[k]) for k in keys if not same(ddp[k], single[k])}
    assert not mismatched, f"DDP vs single-process validation differ: {mismatched}"


@pytest.mark.parametrize(
    "rank_env, expected",
    [
        ({}, True),
        ({"LOCAL_RANK": "1", "NODE_RANK": "0"}, False),
        ({"LOCAL_RANK": "0", "NODE_RANK": "1"}, False),
        ({"LOCAL_RANK": "0", "NODE_RANK": "0", "SLURM_PROCID": "3"}, True),
        ({"RANK": "2", "LOCAL_RANK": "0"}, False),
    ],
)
def test_rank_zero_follows_the_launcher_environment(
    monkeypatch: pytest.MonkeyPatch, rank_env: dict, expected: bool
) -> None:
    from occplug.run import runner

    for key in ("RANK", "LOCAL_RANK", "NODE_RANK", "GROUP_RANK", "SLURM_PROCID"):
        monkeypatch.delenv(key, raising=False)
    for key, value in rank_env.items():
        monkeypatch.setenv(key, value)
    assert runner.is_rank_zero() is expected
    monkeypatch.setenv(runner.RUN_DIR_ENV, "/some/run")
    assert (runner.default_run_dir(["baseline.yaml"]) == Path("/some/run")) is (not expected)


# A stateful model read sequentially: 3 validation scenes of 2 frames, batch 2.
STREAM = [
    "data.sequential=true",
    "data.preset=tiny",
    "data.train_scenes=1",
    "data.val_scenes=3",
    "data.test_scenes=0",
    "data.batch_size=2",
]


# DuOcc's recipes on a 20 x 20 x 8 grid (V_curr 10 x 10 x 4) with a narrower encoder, as in its plugin tests.
DUOCC_SMALL = ["grid.range=[-8.0,-8.0,-1.0,8.0,8.0,5.4]", "model.encoder.out_channels=16", "model.encoder.width=16"]
STREAMING_MODELS = [
    pytest.param(BASELINE, ["model.scene.type=dense_voxels_history"], id="dense_voxels_history"),
    # StreamAgg: V_fin per batch slot, warped into the next frame (reset: V_curr itself)
    pytest.param("duocc/stream_agg", DUOCC_SMALL, id="duocc_stream_agg"),
    # + QueryAgg: a dict state, {voxels: V_fin, detector: the top-k instances}, in one StreamState
    pytest.param("duocc/full", DUOCC_SMALL, id="duocc_full"),
]


@pytest.mark.parametrize("config, model", STREAMING_MODELS)
def test_ddp_streaming_validation_counts_every_frame_once_and_equals_one_process(
    tmp_path: Path, config: str, model: list[str]
) -> None:
    run = tmp_path / "run"
    torch_threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as in each DDP worker
    try:
        assert (
            main(
                [
                    "fit",
                    "-c",
                    config,
                    *model,
                    *STREAM,
                    "trainer.accelerator=cpu",
                    "trainer.enable_progress_bar=false",
                    "trainer.max_steps=2",
                    "--run-dir",
                    str(run),
                ]
            )
            == 0
        )
        ckpt = str(run / "checkpoints" / "last.ckpt")
        single = {}
        for batch in (1, 2):
            out = tmp_path / f"single{batch}.json"
            assert (
                main(
                    [
                        "validate",
                        "--ckpt",
                        ckpt,
                        "--json",
                        str(out),
                        "trainer.devices=1",
                        "trainer.strategy=auto",
                        f"data.batch_size={batch}",
                    ]
                )
                == 0
            )
            single[batch] = json.loads(out.read_text())
            # predict streams too: one file per frame, the same whatever the batch size
            assert (
                main(["predict", "--ckpt", ckpt, "--out", str(tmp_path / f"pred{batch}"), f"data.batch_size={batch}"])
                == 0
            )
        preds = [{p.name: np.load(p)["pred"] for p in (tmp_path / f"pred{b}").glob("*.npz")} for b in (1, 2)]
        assert len(preds[0]) == 6 and preds[0].keys() == preds[1].keys()
        assert all(np.array_equal(preds[0][k], preds[1][k]) for k in preds[0])
    finally:
        torch.set_num_threads(torch_threads)
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    out = tmp_path / "ddp.json"
    # rank 0 plays 2 scenes on 2 lanes, rank 1 one scene (the padded sampler used to count frames twice here)
    cmd = [
        *occplug_command(),
        "validate",
        "--ckpt",
        ckpt,
        "--json",
        str(out),
        "trainer.accelerator=cpu",
        "trainer.devices=2",
        "trainer.strategy=ddp",
        "data.batch_size=2",
    ]
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    ddp = json.loads(out.read_text())
    keys = [k for k in single[1] if k == "mIoU" or k.startswith("IoU")]
    assert len(keys) == 19 and single[1]["IoU"] > 0
    for name, other in (("batch 2", single[2]), ("2 processes", ddp)):
        mismatched = {k: (other[k], single[1][k]) for k in keys if not same(other[k], single[1][k])}
        assert not mismatched, f"{name} vs one process, batch 1: {mismatched}"
