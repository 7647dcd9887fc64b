"""Numbers users can trust: mask settings, self-contained checkpoints, the effective batch and lr scaling."""

import json
from pathlib import Path

import pytest
import torch

from occplug.cli import main
from occplug.config import ConfigError
from occplug.run.runner import load_config
from occplug.run.training import EffectiveBatch, batch_notice, build_optimizer, scaled_lr

ROOT = Path(__file__).resolve().parents[1]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
TINY = ["data.preset=tiny", "trainer.accelerator=cpu", "trainer.enable_progress_bar=false", "trainer.max_steps=3"]


def fit(tmp_path: Path, *overrides: str, name: str = "R") -> Path:
    run = tmp_path / name
    assert main(["fit", "-c", BASELINE, *TINY, *overrides, "--run-dir", str(run)]) == 0
    return run


# ----------------------------------------------------------------------------- masks
def test_masks_are_recorded_in_metrics_json_table_config_and_checkpoint(tmp_path, capsys):
    run = fit(tmp_path, "eval_mask=lidar", "model.supervision.voxel_labels.camera_mask=true")
    out = capsys.readouterr().out
    assert "evaluation mask: lidar | training masks: voxel_labels: camera" in out
    assert "Occ3D mIoU (evaluation mask: lidar)" in out
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["eval_mask"] == "lidar" and metrics["train_masks"] == {"voxel_labels": "camera"}
    info = torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)["occplug"]
    assert info["masks"] == {"eval_mask": "lidar", "train_masks": {"voxel_labels": "camera"}}
    assert "eval_mask: lidar" in (run / "config.yaml").read_text()


def test_eval_mask_defaults_to_camera_and_a_conflicting_metric_mask_is_an_error():
    assert load_config([BASELINE])["eval_mask"] == "camera"
    cfg = load_config([BASELINE], ["metrics=[{type: occ3d_miou, mask: lidar}]"])
    assert cfg["eval_mask"] == "lidar"  # a mask set on the one metric node becomes the run's setting
    with pytest.raises(ConfigError, match=r"metrics.0.mask: 'lidar' differs from eval_mask='camera'"):
        load_config([BASELINE], ["eval_mask=camera", "metrics=[{type: occ3d_miou, mask: lidar}]"])
    with pytest.raises(ConfigError, match=r"eval_mask: unknown mask 'camra'; did you mean 'camera'\?"):
        load_config([BASELINE], ["eval_mask=camra"])
    # the model's eval_mask (which it gives its metrics) is the same one setting
    assert load_config([BASELINE], ["model.eval_mask=none"])["eval_mask"] == "none"
    with pytest.raises(ConfigError, match=r"model.eval_mask: 'none' differs from eval_mask='lidar'"):
        load_config([BASELINE], ["eval_mask=lidar", "model.eval_mask=none"])


# ----------------------------------------------------------------------------- checkpoints
def test_checkpoint_alone_reproduces_the_run_after_its_config_is_deleted(tmp_path, capsys):
    run = fit(tmp_path)
    (run / "config.yaml").unlink()
    saved = json.loads((run / "metrics.json").read_text())
    ckpt = run / "checkpoints" / "last.ckpt"
    info = torch.load(ckpt, weights_only=True)["occplug"]
    assert info["class_names"][17] == "free" and len(info["class_names"]) == 18
    assert info["grid"] == {"range": [-24.0, -24.0, -1.0, 24.0, 24.0, 5.4], "voxel_size": 0.8}  # configs/baseline.yaml
    assert info["plugins"]["occplug"]
    assert {(c["path"], c["type"], c["plugin"]) for c in info["components"]} >= {
        ("model", "occ_model", "occplug"),
        ("model.view_transform", "lss", "occplug"),
        ("data", "synthetic", "occplug"),
    }

    out = tmp_path / "val.json"
    capsys.readouterr()
    assert main(["validate", "--ckpt", str(ckpt), "--json", str(out)]) == 0
    again = json.loads(out.read_text())
    for key in ("mIoU", "IoU", "IoU_car", "IoU_driveable_surface"):
        assert again[key] == saved[key], key
    assert again["eval_mask"] == "camera" and again["train_masks"] == {"voxel_labels": "camera"}
    assert "evaluation mask: camera | training masks: voxel_labels: camera" in capsys.readouterr().out

    # overrides still apply on top of the checkpoint's config
    assert main(["validate", "--ckpt", str(ckpt), "--json", str(out), "eval_mask=none"]) == 0
    assert json.loads(out.read_text())["eval_mask"] == "none"
    assert "Occ3D mIoU (evaluation mask: none)" in capsys.readouterr().out


def test_a_checkpoint_whose_plugin_is_missing_names_the_plugin(tmp_path, capsys):
    run = fit(tmp_path)
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)
    info = ckpt["occplug"]
    info["config"]["model"]["heads"]["occupancy"]["type"] = "fancy_head"
    for comp in info["components"]:
        if comp["path"] == "model.heads.occupancy":
            comp.update(type="fancy_head", plugin="fancy", distribution="occplug-fancy", version="1.2.3")
    info["plugins"]["fancy"] = "1.2.3"
    moved = tmp_path / "moved.ckpt"
    torch.save(ckpt, moved)
    capsys.readouterr()
    assert main(["validate", "--ckpt", str(moved)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert "needs plugin 'fancy' (occplug-fancy 1.2.3) for model.heads.occupancy: head 'fancy_head'" in err
    assert "pip install occplug-fancy==1.2.3" in err


# ----------------------------------------------------------------------------- effective batch
def test_linear_lr_scaling_and_the_notice():
    spec = {"type": "adamw", "lr": 2e-4, "reference_batch": 8, "lr_scaling": "linear"}
    one_gpu = EffectiveBatch(devices=1, per_device=2, accumulation=1)
    assert one_gpu.total == 2
    assert scaled_lr(spec, one_gpu) == pytest.approx(5e-5)
    assert scaled_lr(spec, EffectiveBatch(4, 2, 2)) == pytest.approx(4e-4)
    assert batch_notice(spec, EffectiveBatch(2, 2, 2)) is None  # equal to the reference: nothing to say
    notice = batch_notice(spec, one_gpu)
    assert notice == (
        "notice: effective batch 2 (1 device(s) x 2 per device x 1 accumulation) differs from the "
        "recipe's reference batch 8; learning rate scaled linearly 0.0002 -> 5e-05 (optimizer.lr_scaling=linear)"
    )
    kept = batch_notice({**spec, "lr_scaling": "none"}, one_gpu)
    assert kept.endswith("learning rate kept at 0.0002 (optimizer.lr_scaling=linear would scale it to 5e-05)")
    opt = build_optimizer([torch.nn.Parameter(torch.zeros(1))], spec, one_gpu)
    assert opt.param_groups[0]["lr"] == pytest.approx(5e-5)
    assert scaled_lr({"type": "sgd"}, one_gpu) == torch.optim.SGD([torch.zeros(1, requires_grad=True)]).defaults["lr"]


def test_lr_scaling_needs_a_reference_batch():
    with pytest.raises(ConfigError, match="optimizer.lr_scaling: 'linear' needs optimizer.reference_batch"):
        load_config([BASELINE], ["optimizer.lr_scaling=linear"])
    with pytest.raises(ConfigError, match="optimizer.reference_batch: expected a positive int"):
        load_config([BASELINE], ["optimizer.reference_batch=0"])


def test_fit_logs_the_effective_batch_and_scales_the_lr(tmp_path, capsys):
    run = fit(
        tmp_path, "optimizer.reference_batch=8", "optimizer.lr_scaling=linear", "trainer.accumulate_grad_batches=2"
    )
    assert (
        "notice: effective batch 4 (1 device(s) x 2 per device x 2 accumulation) differs from the recipe's "
        "reference batch 8; learning rate scaled linearly 0.002 -> 0.001" in capsys.readouterr().err
    )
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["effective_batch"] == 4 and metrics["lr"] == pytest.approx(1e-3)
    assert metrics["effective_batch_parts"] == {"devices": 1, "per_device": 2, "accumulation": 2}
    logged = (run / "logs" / "version_0" / "metrics.csv").read_text().splitlines()
    header = logged[0].split(",")
    values = [row.split(",")[header.index("train/effective_batch")] for row in logged[1:]]
    assert "4.0" in values
