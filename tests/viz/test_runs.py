"""Run pictures: curves from every CSV log version, per-class IoU bars from metrics.json."""

import json
import math

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from occplug.viz.runs import class_iou_figure, curves_figure, plot_run, read_logs  # noqa: E402


def _write_run(root):
    v0 = root / "logs" / "version_0"
    v1 = root / "logs" / "version_1"
    v0.mkdir(parents=True)
    v1.mkdir(parents=True)
    head = "epoch,step,train/loss,train/voxel_labels/voxel_ce,val/IoU,val/IoU_car,val/loss,val/mIoU\n"
    (v0 / "metrics.csv").write_text(head + "0,0,3.0,3.0,,,,\n0,1,2.5,2.5,,,,\n0,1,,,40.0,10.0,2.6,20.0\n")
    (v1 / "metrics.csv").write_text(head + "1,2,2.0,2.0,,,,\n1,3,1.5,1.5,,,,\n1,3,,,50.0,30.0,1.9,25.0\n")
    metrics = {
        "mIoU": 25.0,
        "IoU": 50.0,
        "IoU_car": 30.0,
        "IoU_truck": float("nan"),
        "IoU_driveable_surface": 90.0,
        "global_step": 4,
        "epoch": 1,
    }
    (root / "metrics.json").write_text(json.dumps(metrics))


def test_read_logs_concatenates_versions(tmp_path):
    _write_run(tmp_path)
    logs = read_logs(tmp_path)
    assert logs.versions == [0, 1]
    x, y = logs.series("train/loss")
    assert x.tolist() == [0, 1, 2, 3] and y.tolist() == [3.0, 2.5, 2.0, 1.5]
    x, y = logs.series("val/mIoU")
    assert x.tolist() == [1, 3] and y.tolist() == [20.0, 25.0]
    assert logs.resume_steps() == [(1, 2.0)]


def test_curves_group_losses_and_metrics_and_mark_resumes(tmp_path):
    _write_run(tmp_path)
    fig = curves_figure(read_logs(tmp_path), title="run")
    titles = [ax.get_title() for ax in fig.axes]
    assert titles == ["losses", "validation metrics"]
    labels = {ax.get_title(): [t.get_text() for t in ax.get_legend().get_texts()] for ax in fig.axes}
    assert labels["losses"] == ["train/loss", "train/voxel_labels/voxel_ce", "val/loss"]
    assert labels["validation metrics"] == ["val/IoU", "val/mIoU"]  # per-class columns left out
    assert any("resume (v1)" in t.get_text() for t in fig.axes[0].texts)


def test_class_iou_bars_in_class_colours(tmp_path):
    _write_run(tmp_path)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    fig = class_iou_figure(metrics, title="run")
    ax = fig.axes[0]
    assert [t.get_text() for t in ax.get_xticklabels()] == ["car", "truck", "driveable_surface"]
    bars = ax.patches
    assert [b.get_height() for b in bars] == [30.0, 0.0, 90.0]
    assert np.allclose(bars[0].get_facecolor()[:3], np.array([0, 150, 245]) / 255)  # Occ3D car blue
    notes = [t.get_text() for t in ax.texts]
    assert notes == ["30.0", "n/a", "90.0"]
    assert "mIoU = 25.00" in fig._suptitle.get_text()
    assert math.isclose(float(ax.get_legend().get_texts()[0].get_text().split("= ")[1]), 60.0)


def test_plot_run_writes_both_pngs(tmp_path):
    _write_run(tmp_path / "run")
    written = plot_run(tmp_path / "run", tmp_path / "out")
    assert sorted(p.name for p in written) == ["class_iou.png", "curves.png"]
    assert all(p.stat().st_size > 5_000 for p in written)


def test_plot_run_on_a_folder_without_logs(tmp_path):
    with pytest.raises(FileNotFoundError, match="not an occplug run directory"):
        plot_run(tmp_path)
