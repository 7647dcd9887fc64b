"""The CLI contract: exit codes, one-line errors, run directories, resume, evaluate, predict."""

import importlib.metadata
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from occplug.cli import main

ROOT = Path(__file__).resolve().parents[2]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
TINY = ["data.preset=tiny", "trainer.accelerator=cpu", "trainer.enable_progress_bar=false"]


def run_cli(*args, cwd=ROOT):
    """The real console script in a subprocess (exit code, stdout, stderr)."""
    proc = subprocess.run(
        [sys.executable, "-m", "occplug.cli", *args], cwd=cwd, capture_output=True, text=True, env={**os.environ}
    )
    return proc.returncode, proc.stdout, proc.stderr


def test_config_show_applies_override(capsys):
    wired = "model.view_transform.out_channels=${model.scene.out_channels}"
    assert main(["config", "show", "-c", BASELINE, "trainer.max_epochs=3", wired]) == 0
    cfg = yaml.safe_load(capsys.readouterr().out)
    assert cfg["trainer"]["max_epochs"] == 3
    assert cfg["model"]["view_transform"]["out_channels"] == cfg["model"]["scene"]["out_channels"]  # resolved
    assert "grid" not in cfg["model"]["view_transform"]  # the model gives it the top-level grid


def test_config_show_explain(capsys):
    assert main(["config", "show", "-c", BASELINE, "trainer.max_epochs=3", "--explain", "trainer.max_epochs"]) == 0
    assert capsys.readouterr().out.strip() == "trainer.max_epochs: set by override trainer.max_epochs=3"


def test_misspelt_key_exits_2_with_one_line_suggestion():
    code, out, err = run_cli("fit", "-c", BASELINE, "model.view_transfrom.type=lss")
    assert code == 2
    assert err.strip().count("\n") == 0 and "Traceback" not in err
    assert "model.view_transfrom" in err and "did you mean 'view_transform'?" in err


def test_unknown_type_exits_2_listing_available(capsys):
    assert main(["fit", "-c", BASELINE, "model.view_transform.type=lsss"]) == 2
    err = capsys.readouterr().err
    assert "model.view_transform.type: no view_transform named 'lsss'; did you mean 'lss'?" in err
    assert "backward_projection" in err


def test_missing_config_file_exits_2(capsys, tmp_path):
    assert main(["fit", "-c", str(tmp_path / "nope.yaml"), "--run-dir", str(tmp_path / "r")]) == 2
    assert "not found" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()  # nothing written half-way


def test_fit_writes_run_dir_then_resume_validate_predict(tmp_path, capsys):
    run = tmp_path / "R"
    assert main(["fit", "-c", BASELINE, *TINY, "trainer.max_steps=5", "--run-dir", str(run)]) == 0
    assert (run / "config.yaml").is_file() and (run / "checkpoints" / "last.ckpt").is_file()
    metrics = json.loads((run / "metrics.json").read_text())
    assert "mIoU" in metrics and metrics["global_step"] == 5
    assert "occplug" in json.loads((run / "plugins.json").read_text())
    environment = json.loads((run / "environment.json").read_text())
    assert environment["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert environment["packages"]["torch"] == importlib.metadata.version("torch")
    assert (run / "logs" / "version_0" / "metrics.csv").is_file()
    saved = yaml.safe_load((run / "config.yaml").read_text())
    assert saved["trainer"]["max_steps"] == 5 and saved["data"]["preset"] == "tiny"

    # the same directory again is refused (exit 2), resume continues from the last checkpoint
    assert main(["fit", "-c", BASELINE, *TINY, "--run-dir", str(run)]) == 2
    assert "already exists" in capsys.readouterr().err
    assert main(["fit", "--resume", str(run), "trainer.max_steps=7"]) == 0
    assert json.loads((run / "metrics.json").read_text())["global_step"] == 7
    assert (run / "logs" / "version_0" / "metrics.csv").is_file() and (run / "logs" / "version_1").is_dir()

    # validate with the checkpoint alone (config stored inside) and with -c
    out_json = tmp_path / "val.json"
    assert main(["validate", "--ckpt", str(run / "checkpoints" / "last.ckpt"), "--json", str(out_json)]) == 0
    assert "Occ3D mIoU (evaluation mask: camera)" in capsys.readouterr().out
    val = json.loads(out_json.read_text())
    assert val["mIoU"] == pytest.approx(json.loads((run / "metrics.json").read_text())["mIoU"], abs=1e-4)

    preds = tmp_path / "P"
    assert (
        main(["predict", "-c", BASELINE, *TINY, "--ckpt", str(run / "checkpoints" / "last.ckpt"), "--out", str(preds)])
        == 0
    )
    files = sorted(preds.glob("*.npz"))
    assert files
    arr = np.load(files[0])["pred"]
    assert arr.dtype == np.uint8 and arr.shape == (60, 60, 8)


def test_validate_missing_checkpoint_exits_2(capsys, tmp_path):
    assert main(["validate", "-c", BASELINE, "--ckpt", str(tmp_path / "none.ckpt")]) == 2
    assert "does not exist" in capsys.readouterr().err
