"""Metrics chosen by the config's ``metrics:`` list, end to end through a fit."""

import json
from pathlib import Path

from occplug.geometry import GridSpec
from occplug.metrics import Occ3DMIoU, RayIoU
from occplug.run import runner
from occplug.testing import run_config

BASELINE = str(Path(__file__).resolve().parents[2] / "configs" / "baseline.yaml")


def test_occ3d_style_run_reports_miou_and_rayiou(tmp_path, capsys):
    results = run_config(BASELINE, run_dir=tmp_path / "run", overrides=["metrics=[occ3d_miou, rayiou]"])
    assert {"mIoU", "IoU", "RayIoU", "RayIoU_1m", "RayIoU_2m", "RayIoU_4m", "RayIoU_car"} <= set(results)
    assert 0 <= results["RayIoU"] <= 100
    saved = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert saved["RayIoU"] == results["RayIoU"] and saved["mIoU"] == results["mIoU"]
    out = capsys.readouterr().out
    assert "Occ3D mIoU (evaluation mask: camera)" in out
    assert "RayIoU (SparseOcc / Occ3D-nuScenes leaderboard; thresholds 1, 2, 4 m;" in out
    assert "grid 60x60x8 @ 0.8/0.8/0.8 m" in out  # the run's grid reached the metric


def test_ssc_run_reports_completion_and_semantic_scores(tmp_path, capsys):
    results = run_config(BASELINE, run_dir=tmp_path / "run", overrides=["metrics=[ssc]"])
    assert {"IoU", "mIoU", "Precision", "Recall", "IoU_car"} <= set(results)
    assert "RayIoU" not in results
    assert "SemanticKITTI SSC (semantic-kitti-api scorer; empty = free (17)" in capsys.readouterr().out


def _small_model(**kwargs):
    from occplug.model import OccModel

    return OccModel(
        encoder={"type": "small_cnn", "out_channels": 8, "width": 8, "stride": 4},
        view_transform={"type": "lss", "out_channels": 8, "hidden": 0, "depth_bins": [1.0, 41.0, 2.0]},
        scene={"type": "dense_voxels", "out_channels": 8, "num_blocks": 0},
        heads={"occupancy": {"type": "voxel_classifier", "hidden": 8}},
        supervision={},
        grid={"range": [-8.0, -8.0, -1.0, 8.0, 8.0, 2.2], "voxel_size": 0.8},
        context=_context({"range": [-8.0, -8.0, -1.0, 8.0, 8.0, 2.2], "voxel_size": 0.8}),
        **kwargs,
    )


def _context(grid):
    from occplug.context import RunContext
    from occplug.data.classes import OCC3D_CLASSES
    from occplug.plugins import get_registry

    # the Occ3D taxonomy: 18 classes, as the model assumed before it took its classes from the run context
    return RunContext(
        GridSpec.from_config(grid), OCC3D_CLASSES, free_label=17, ignore_label=255, registry=get_registry()
    )


def test_the_model_gives_the_eval_mask_to_metrics_that_take_one():
    metrics = ["occ3d_miou", "rayiou", {"type": "occ3d_miou", "mask": "none"}, "ssc"]
    miou, rayiou, own, ssc = _small_model(metrics=metrics, eval_mask="lidar").val_metrics.values()
    assert (miou.mask, own.mask) == ("lidar", "none")  # a node's own mask stays
    assert isinstance(rayiou, RayIoU) and not hasattr(ssc, "mask")
    assert _small_model(metrics=["occ3d_miou"]).val_metrics["occ3d_miou"].mask == "camera"  # none given: its default
    assert isinstance(Occ3DMIoU(), Occ3DMIoU)


def test_the_runner_gives_the_run_eval_mask_to_the_model():
    cfg = runner.load_config([BASELINE, "occplug/trainer/debug"], ["eval_mask=lidar", "metrics=[occ3d_miou, rayiou]"])
    dm = runner.build_datamodule(cfg)
    model = runner.build_model(cfg, dm)
    assert model.eval_mask == "lidar" and model.val_metrics["occ3d_miou"].mask == "lidar"
    assert model.test_metrics["occ3d_miou"].mask == "lidar"


def test_the_model_gives_its_grid_to_metrics_that_leave_it_out():
    from occplug.model import OccModel

    grid = {"range": [-8.0, -8.0, -1.0, 8.0, 8.0, 2.2], "voxel_size": 0.8}
    own = {"range": [0.0, 0.0, 0.0, 4.0, 4.0, 4.0], "voxel_size": 1.0}
    model = OccModel(
        encoder={"type": "small_cnn", "out_channels": 8, "width": 8, "stride": 4},
        view_transform={"type": "lss", "out_channels": 8, "hidden": 0, "depth_bins": [1.0, 41.0, 2.0]},
        scene={"type": "dense_voxels", "out_channels": 8, "num_blocks": 0},
        heads={"occupancy": {"type": "voxel_classifier", "hidden": 8}},
        supervision={},
        grid=grid,
        metrics=["rayiou", {"type": "rayiou", "grid": own}],
        context=_context(grid),
    )
    first, second = model.val_metrics.values()
    assert first.grid == GridSpec.from_config(grid) and second.grid == GridSpec.from_config(own)
    assert model.view_transform.grid == GridSpec.from_config(grid)  # the view transform's node names no grid
