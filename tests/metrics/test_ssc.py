"""SemanticKITTI SSC metrics: hand-computed cases and agreement with the benchmark scorer's arithmetic."""

import math

import numpy as np
import torch
from metric_batches import make_batch

from occplug.data.classes import SEMANTIC_KITTI_CLASSES
from occplug.metrics import SSCMetrics


def scorer(pred, target, invalid, n_classes=20):
    """semantic-kitti-api's evaluate_completion.py + np_ioueval.py, transcribed in numpy."""
    mask = (target != 255) & (invalid != 1)
    pred, target = pred[mask], target[mask]
    conf = np.zeros((n_classes, n_classes), dtype=np.int64)  # rows = prediction, columns = target
    np.add.at(conf, (pred, target), 1)
    tp = np.diag(conf)
    iou = tp / (tp + (conf.sum(1) - tp) + (conf.sum(0) - tp) + 1e-15)
    eps = np.finfo(np.float32).eps
    return {
        "mIoU": iou[1:].mean(),
        "IoU": conf[1:, 1:].sum() / (conf.sum() - conf[0, 0]),
        "Precision": conf[1:, 1:].sum() / (conf[1:, :].sum() + eps),
        "Recall": conf[1:, 1:].sum() / (conf[:, 1:].sum() + eps),
        "iou": iou,
    }


def test_hand_computed_ssc():
    # ids: 0 empty; 1, 2 semantic; voxel 6 ignored (255), voxel 7 invalid
    gt = torch.tensor([0, 0, 1, 1, 2, 0, 255, 1]).reshape(1, 2, 2, 2)
    pred = torch.tensor([0, 1, 1, 2, 2, 0, 1, 0]).reshape(1, 2, 2, 2)
    invalid = torch.tensor([0, 0, 0, 0, 0, 0, 0, 1], dtype=torch.bool).reshape(1, 2, 2, 2)
    m = SSCMetrics(num_classes=3, class_names=["empty", "a", "b"], free_label=0)
    m.update(pred, make_batch(gt, voxel_invalid=invalid))
    res = m.compute()
    # evaluated voxels 0-5: class a: tp 1 (v2), fp 1 (v1), fn 1 (v3) -> 1/3; class b: tp 1, fp 1 (v3) -> 1/2
    assert math.isclose(res["IoU_a"].item(), 100 / 3, rel_tol=1e-6)
    assert math.isclose(res["IoU_b"].item(), 50, rel_tol=1e-6)
    assert math.isclose(res["mIoU"].item(), (100 / 3 + 50) / 2, rel_tol=1e-6)
    # completion: occupied gt {2, 3, 4}, pred {1, 2, 3, 4}: both 3, union 4
    assert math.isclose(res["IoU"].item(), 75, rel_tol=1e-6)
    assert math.isclose(res["Precision"].item(), 75, rel_tol=1e-6) and math.isclose(
        res["Recall"].item(), 100, rel_tol=1e-6
    )
    assert m.confmat.sum() == 6  # the ignored and the invalid voxel are not counted


def test_absent_class_counts_as_zero_in_the_mean_like_the_benchmark():
    gt = torch.tensor([0, 1, 1, 0]).reshape(1, 1, 2, 2)
    m = SSCMetrics(num_classes=3, free_label=0)
    m.update(gt.clone(), make_batch(gt))
    res = m.compute()
    assert res["IoU"].item() == 100 and res["IoU_class_1"].item() == 100
    assert res["IoU_class_2"].item() == 0 and math.isclose(res["mIoU"].item(), 50, rel_tol=1e-6)


def test_empty_prediction_and_one_voxel():
    gt = torch.zeros(1, 4, 4, 2, dtype=torch.long)
    gt[0, 1, 2, 1] = 5
    m = SSCMetrics()
    m.update(torch.zeros_like(gt), make_batch(gt))
    res = m.compute()
    assert res["IoU"].item() == 0 and res["mIoU"].item() == 0 and res["Recall"].item() == 0
    m.reset()
    m.update(gt.clone(), make_batch(gt))
    res = m.compute()
    assert res["IoU"].item() == 100 and res["IoU_other-vehicle"].item() == 100
    assert math.isclose(res["mIoU"].item(), 100 / 19, rel_tol=1e-6)  # one of 19 classes present


def test_random_volumes_match_the_benchmark_scorer():
    gen = torch.Generator().manual_seed(0)
    shape = (3, 16, 16, 4)
    gt = torch.randint(0, 20, shape, generator=gen)
    gt[torch.rand(shape, generator=gen) < 0.4] = 0
    gt[torch.rand(shape, generator=gen) < 0.05] = 255
    pred = torch.where(
        torch.rand(shape, generator=gen) < 0.7, gt.clamp(max=19), torch.randint(0, 20, shape, generator=gen)
    )
    invalid = torch.rand(shape, generator=gen) < 0.1
    m = SSCMetrics()
    for b in range(shape[0]):  # accumulates over batches like the scorer over scans
        m.update(pred[b : b + 1], make_batch(gt[b : b + 1], voxel_invalid=invalid[b : b + 1]))
    res = m.compute()
    ref = scorer(pred.numpy(), gt.numpy(), invalid.numpy())
    for key in ("mIoU", "IoU", "Precision", "Recall"):
        assert math.isclose(res[key].item(), ref[key] * 100, rel_tol=1e-5), key
    for c in range(1, 20):
        assert math.isclose(
            res[f"IoU_{SEMANTIC_KITTI_CLASSES[c]}"].item(), ref["iou"][c] * 100, rel_tol=1e-5, abs_tol=1e-6
        )


def test_table_is_the_benchmark_list_with_settings():
    gt = torch.tensor([0, 1]).reshape(1, 1, 1, 2)
    m = SSCMetrics()
    m.update(gt, make_batch(gt))
    lines = m.table().splitlines()
    assert lines[0].startswith("SemanticKITTI SSC (semantic-kitti-api scorer; empty = empty (0), ignore label 255")
    assert [line.split()[0] for line in lines[2:21]] == list(SEMANTIC_KITTI_CLASSES[1:])
    assert lines[21].startswith("mIoU (SSC)") and lines[22].startswith("IoU (completion)")


def test_dynamic_and_static_mious_are_the_scorer_mean_over_the_core_groups():
    from occplug.data.classes import class_groups

    gen = torch.Generator().manual_seed(3)
    gt = torch.randint(0, 20, (2, 8, 8, 4), generator=gen)
    pred = torch.where(torch.rand(gt.shape, generator=gen) < 0.6, gt, torch.randint(0, 20, gt.shape, generator=gen))
    m = SSCMetrics()
    m.update(pred, make_batch(gt))
    res = m.compute()
    ref = scorer(pred.numpy(), gt.numpy(), np.zeros(gt.shape, dtype=np.int64))
    groups = class_groups(SEMANTIC_KITTI_CLASSES)
    for key in ("dynamic", "static"):
        assert math.isclose(res[f"mIoU_{key}"].item(), ref["iou"][list(groups[key])].mean() * 100, rel_tol=1e-5)
    assert "mIoU dynamic" in m.table() and "mIoU static" in m.table()
    assert "mIoU_dynamic" not in SSCMetrics(num_classes=3, free_label=0).compute()  # no groups for an unknown taxonomy


def test_excluded_classes_are_left_out_of_the_plain_means():
    import pytest

    gen = torch.Generator().manual_seed(3)
    gt = torch.randint(0, 20, (1, 8, 8, 4), generator=gen)
    pred = torch.where(torch.rand(gt.shape, generator=gen) < 0.7, gt, torch.randint(0, 20, gt.shape, generator=gen))
    m = SSCMetrics(exclude_classes=["person", "road"])
    m.update(pred, make_batch(gt))
    res = m.compute()
    iou = {n: res[f"IoU_{n}"].item() for n in SEMANTIC_KITTI_CLASSES[1:]}
    kept = [n for n in iou if n not in ("person", "road")]
    assert math.isclose(res["mIoU_excl"].item(), float(np.mean([iou[n] for n in kept])), rel_tol=1e-5)
    dynamic = [n for n in kept if SEMANTIC_KITTI_CLASSES.index(n) <= 8]
    static = [n for n in kept if SEMANTIC_KITTI_CLASSES.index(n) > 8]
    assert math.isclose(res["mIoU_dynamic_excl"].item(), float(np.mean([iou[n] for n in dynamic])), rel_tol=1e-5)
    assert math.isclose(res["mIoU_static_excl"].item(), float(np.mean([iou[n] for n in static])), rel_tol=1e-5)
    assert res["mIoU_excl"] != res["mIoU"] and "without person, road:" in m.table()
    with pytest.raises(ValueError, match="ssc.exclude_classes: unknown class 'empty'"):
        SSCMetrics(exclude_classes=["empty"])
