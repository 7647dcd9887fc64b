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


def _metric_keys(metric) -> list[str]:
    """The keys ``metric.compute()`` writes (its values are NaN here: no update)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return list(metric.compute())


def _bars(ax):
    names = [t.get_text() for t in ax.get_xticklabels()]
    return dict(zip(names, [b.get_height() for b in ax.patches], strict=True))


def _mean_line(ax) -> float:
    return float(ax.get_legend().get_texts()[0].get_text().split("= ")[1])


def test_class_iou_takes_per_class_keys_not_rayiou_thresholds():
    from occplug.data.classes import OCC3D_CLASSES, OCC3D_FREE
    from occplug.metrics import Occ3DMIoU, RayIoU

    classes = [c for i, c in enumerate(OCC3D_CLASSES) if i != OCC3D_FREE]
    excl = ["traffic_cone", "others"]
    keys = _metric_keys(Occ3DMIoU(class_names=OCC3D_CLASSES, exclude_classes=excl))
    keys += _metric_keys(RayIoU(class_names=OCC3D_CLASSES, exclude_classes=excl))
    assert {"RayIoU_1m", "RayIoU_2m", "RayIoU_4m", "RayIoU_car", "IoU_car", "mIoU", "IoU", "RayIoU"} <= set(keys)
    groups = {
        "RayIoU_dynamic": 30.0,
        "RayIoU_static": 36.0,
        "RayIoU_geometry": 60.0,
        "RayIoU_excl": 34.0,
        "RayIoU_dynamic_excl": 31.0,
        "RayIoU_static_excl": 37.0,
        "mIoU_excl": 19.0,
        "mIoU_dynamic_excl": 16.0,
        "mIoU_static_excl": 24.0,
    }
    assert set(groups) <= set(keys)
    iou = {c: 10.0 + i for i, c in enumerate(classes)}
    ray = {c: 50.0 - 2 * i for i, c in enumerate(classes)}
    ray["bus"] = float("nan")  # absent from truth and prediction: skipped by the mean, as RayIoU does
    summary = {
        "mIoU": 18.0,
        "IoU": 55.0,
        "RayIoU": 33.0,
        "RayIoU_1m": 21.0,
        "RayIoU_2m": 31.0,
        "RayIoU_4m": 47.0,
        "mIoU_dynamic": 15.0,
        "mIoU_static": 23.0,
        **groups,
    }
    metrics = {"global_step": 10, "epoch": 1}
    for key in keys:
        family, _, cls = key.partition("_")
        metrics[key] = summary[key] if key in summary else (iou if family == "IoU" else ray)[cls]
    fig = class_iou_figure(metrics)
    titles = [ax.get_title() for ax in fig.axes]
    assert titles == ["per-class IoU", "per-class RayIoU (mean over 1m, 2m, 4m)"]
    iou_ax, ray_ax = fig.axes
    assert _bars(iou_ax) == iou  # exactly the 17 semantic classes, in id order
    assert list(_bars(ray_ax)) == classes  # no 1m / 2m / 4m, group, geometry or _excl bars
    assert math.isclose(_mean_line(iou_ax), float(np.mean(list(iou.values()))), abs_tol=0.01)
    assert math.isclose(_mean_line(ray_ax), float(np.nanmean(list(ray.values()))), abs_tol=0.01)
    headline = fig._suptitle.get_text()
    for key in (
        "mIoU = 18.00",
        "RayIoU = 33.00",
        "RayIoU_1m = 21.00",
        "RayIoU_2m = 31.00",
        "RayIoU_4m = 47.00",
        "mIoU_dynamic = 15.00",
        "mIoU_static = 23.00",
    ):  # group means are headline values, not bars
        assert key in headline
    assert all(f"{k} = {v:.2f}" in headline for k, v in groups.items())
    assert "global_step" not in headline and "epoch" not in headline


def test_class_iou_of_ssc_keys_in_semantickitti_colours():
    from occplug.data.classes import SEMANTIC_KITTI_CLASSES, SEMANTIC_KITTI_COLORS
    from occplug.metrics import SSCMetrics

    keys = _metric_keys(SSCMetrics())
    classes = list(SEMANTIC_KITTI_CLASSES[1:])
    values = {c: 3.0 * i for i, c in enumerate(classes)}  # SSC scores absent classes 0, not NaN
    summary = {"IoU": 40.0, "mIoU": float(np.mean(list(values.values()))), "Precision": 60.0, "Recall": 50.0}
    summary |= {"mIoU_dynamic": 10.0, "mIoU_static": 20.0}  # headline values, not classes
    metrics = {k: summary[k] if k in summary else values[k.partition("_")[2]] for k in keys}
    fig = class_iou_figure(metrics)
    (ax,) = fig.axes
    assert _bars(ax) == values
    assert math.isclose(_mean_line(ax), summary["mIoU"], abs_tol=0.01)  # the mean line is the SSC mIoU
    car = ax.patches[classes.index("car")]
    assert np.allclose(car.get_facecolor()[:3], np.array(SEMANTIC_KITTI_COLORS[1]) / 255)  # not Occ3D's car blue
    assert all(f"{k} = {v:.2f}" in fig._suptitle.get_text() for k, v in summary.items())


def test_curves_show_rayiou_thresholds_but_not_classes(tmp_path):
    v0 = tmp_path / "logs" / "version_0"
    v0.mkdir(parents=True)
    head = "epoch,step,val/RayIoU,val/RayIoU_1m,val/RayIoU_car,val/IoU_car,val/mIoU\n"
    (v0 / "metrics.csv").write_text(head + "0,1,30.0,20.0,25.0,10.0,15.0\n")
    fig = curves_figure(read_logs(tmp_path))
    (ax,) = fig.axes
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["val/RayIoU", "val/RayIoU_1m", "val/mIoU"]
