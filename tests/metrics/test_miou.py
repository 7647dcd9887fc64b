import math

import pytest
import torch

from occplug.metrics import Occ3DMIoU, confusion_matrix
from occplug.testing import label_batch


def make_batch(labels, mask_camera=None, mask_lidar=None):
    return label_batch(labels, mask_camera=mask_camera, mask_lidar=mask_lidar)


def test_confusion_matrix_ignores_255_and_invalid():
    target = torch.tensor([0, 1, 1, 255, 2])
    pred = torch.tensor([0, 1, 2, 0, 2])
    cm = confusion_matrix(pred, target, 3, valid=torch.tensor([True, True, True, True, False]))
    assert cm.tolist() == [[1, 0, 0], [0, 1, 1], [0, 0, 0]]


def test_hand_computed_miou_and_geometric_iou():
    # 4 classes, free = 3. Voxels: gt  [0, 0, 1, 1, 3, 3, 2, 3]
    #                           pred [0, 1, 1, 1, 3, 0, 3, 3]
    gt = torch.tensor([0, 0, 1, 1, 3, 3, 2, 3]).reshape(1, 2, 2, 2)
    pred = torch.tensor([0, 1, 1, 1, 3, 0, 3, 3]).reshape(1, 2, 2, 2)
    m = Occ3DMIoU(num_classes=4, class_names=["a", "b", "c", "free"], free_label=3, mask="none")
    m.update(pred, make_batch(gt))
    res = m.compute()
    # class 0: tp 1, fp 1 (voxel 5), fn 1 (voxel 1) -> 1/3; class 1: tp 2, fp 1 -> 2/3; class 2: tp 0, fn 1 -> 0
    assert math.isclose(res["IoU_a"].item(), 100 / 3, rel_tol=1e-5)
    assert math.isclose(res["IoU_b"].item(), 200 / 3, rel_tol=1e-5)
    assert res["IoU_c"].item() == 0
    assert math.isclose(res["mIoU"].item(), 100 / 3, rel_tol=1e-5)
    # geometry: occupied gt {0,1,2,3,6}, pred occupied {0,1,2,3,5}: tp 4, fp 1, fn 1 -> 4/6
    assert math.isclose(res["IoU"].item(), 400 / 6, rel_tol=1e-5)


def test_absent_class_is_skipped_and_perfect_prediction_scores_100():
    gt = torch.tensor([0, 3, 3, 0]).reshape(1, 1, 2, 2)
    m = Occ3DMIoU(num_classes=4, free_label=3, mask="none")
    m.update(gt.clone(), make_batch(gt))
    res = m.compute()
    assert res["mIoU"].item() == 100 and res["IoU"].item() == 100
    assert math.isnan(res["IoU_class_1"].item())


def test_camera_mask_selects_voxels_and_accumulates_over_batches():
    gt = torch.tensor([0, 0, 3, 3]).reshape(1, 1, 2, 2)
    pred = torch.tensor([0, 3, 3, 0]).reshape(1, 1, 2, 2)
    mask = torch.tensor([True, False, True, False]).reshape(1, 1, 2, 2)
    m = Occ3DMIoU(num_classes=4, free_label=3, mask="camera")
    m.update(pred, make_batch(gt, mask_camera=mask))
    assert m.compute()["mIoU"].item() == 100  # the two wrong voxels are outside the mask
    m.update(pred, make_batch(gt, mask_camera=~mask))
    assert m.confmat.sum().item() == 4
    both = Occ3DMIoU(num_classes=4, free_label=3, mask="camera_and_lidar")
    both.update(pred, make_batch(gt, mask_camera=mask, mask_lidar=torch.zeros_like(mask)))
    assert both.confmat.sum().item() == 0


def test_missing_mask_is_a_clear_error():
    gt = torch.zeros(1, 1, 2, 2, dtype=torch.long)
    with pytest.raises(ValueError, match="evaluation mask 'camera' needs batch field.*mask_camera"):
        Occ3DMIoU(num_classes=4, free_label=3).update(gt, make_batch(gt))


def test_table_names_the_mask():
    gt = torch.tensor([0, 3]).reshape(1, 1, 1, 2)
    m = Occ3DMIoU(num_classes=4, free_label=3, mask="none")
    m.update(gt, make_batch(gt))
    assert m.table().startswith("Occ3D mIoU (evaluation mask: none)")


def test_each_evaluation_mask_gives_its_hand_computed_scores():
    # four voxels along y, classes a, b, b, free; the prediction gets voxel 1 wrong (a) and voxel 3 wrong (b)
    gt = torch.tensor([0, 1, 1, 3]).reshape(1, 1, 4, 1)
    pred = torch.tensor([0, 0, 1, 1]).reshape(1, 1, 4, 1)
    camera = torch.tensor([True, True, False, True]).reshape(1, 1, 4, 1)
    lidar = torch.tensor([True, False, True, True]).reshape(1, 1, 4, 1)
    batch = make_batch(gt, mask_camera=camera, mask_lidar=lidar)
    expected = {
        # voxels 0-3: a: TP 1, FP 1 (voxel 1) -> 1/2; b: TP 1, FN 1 (voxel 1), FP 1 (voxel 3) -> 1/3; c absent
        "none": (100 * (1 / 2 + 1 / 3) / 2, 100 * 3 / 4),
        # voxels 0, 1, 3: a: TP 1, FP 1 -> 1/2; b: FN 1, FP 1 -> 0; geometry: TP 2 (0, 1), FP 1 (3) -> 2/3
        "camera": (100 * (1 / 2 + 0) / 2, 100 * 2 / 3),
        # voxels 0, 2, 3: a: 1/1; b: TP 1, FP 1 -> 1/2; geometry: TP 2, FP 1 -> 2/3
        "lidar": (100 * (1 + 1 / 2) / 2, 100 * 2 / 3),
        # voxels 0, 3: a: 1/1; b: FP 1 -> 0; geometry: TP 1, FP 1 -> 1/2
        "camera_and_lidar": (100 * (1 + 0) / 2, 100 * 1 / 2),
    }
    for mask, (miou, iou) in expected.items():
        m = Occ3DMIoU(num_classes=4, free_label=3, mask=mask)
        m.update(pred, batch)
        res = m.compute()
        assert res["mIoU"].item() == pytest.approx(miou, abs=1e-4), mask
        assert res["IoU"].item() == pytest.approx(iou, abs=1e-4), mask
        assert m.table().startswith(f"Occ3D mIoU (evaluation mask: {mask})")


def test_a_predicted_id_outside_the_classes_is_an_error():
    m = Occ3DMIoU(num_classes=4, free_label=3, mask="none")
    with pytest.raises(ValueError, match="the prediction holds class id 255, outside 0..3"):
        m.update(torch.full((1, 1, 2, 2), 255), make_batch(torch.zeros(1, 1, 2, 2, dtype=torch.long)))


def test_dynamic_and_static_miou_by_hand():
    from occplug.data.classes import OCC3D_CLASSES, OCC3D_DYNAMIC, OCC3D_STATIC, SEMANTIC_KITTI_CLASSES, class_groups

    # the one definition: ten objects dynamic, six surfaces static, others and free in neither
    groups = class_groups(OCC3D_CLASSES)
    assert groups == {"dynamic": tuple(range(1, 11)), "static": tuple(range(11, 17))}
    assert "barrier" in OCC3D_DYNAMIC and "traffic_cone" in OCC3D_DYNAMIC and "others" not in OCC3D_STATIC
    kitti = class_groups(SEMANTIC_KITTI_CLASSES)
    assert kitti["dynamic"] == tuple(range(1, 9)) and kitti["static"] == tuple(range(9, 20))
    assert class_groups(["a", "b"]) is None
    # Occ3D ids: 0 others, 4 car, 7 pedestrian, 11 driveable_surface, 16 vegetation, 17 free
    gt = torch.tensor([0, 4, 4, 7, 11, 11, 16, 17])
    pred = torch.tensor([4, 4, 17, 7, 11, 16, 16, 17])
    m = Occ3DMIoU(num_classes=18, class_names=OCC3D_CLASSES, free_label=17, mask="none")
    m.update(pred.reshape(1, 2, 2, 2), make_batch(gt.reshape(1, 2, 2, 2)))
    res = m.compute()
    # car: tp 1, fp 1 (others voxel), fn 1 -> 1/3; pedestrian 1; other dynamic classes absent (NaN, skipped)
    assert math.isclose(res["mIoU_dynamic"].item(), 100 * (1 / 3 + 1) / 2, rel_tol=1e-5)
    # driveable: tp 1, fn 1 -> 1/2; vegetation: tp 1, fp 1 -> 1/2
    assert math.isclose(res["mIoU_static"].item(), 50.0, rel_tol=1e-5)
    # others: tp 0, fn 1 -> 0 counts in mIoU but in neither group
    assert math.isclose(res["mIoU"].item(), 100 * (0 + 1 / 3 + 1 + 0.5 + 0.5) / 5, rel_tol=1e-5)
    assert "mIoU dynamic" in m.table()
    # explicit groups for another taxonomy; no groups -> no keys
    custom = Occ3DMIoU(
        num_classes=4,
        class_names=["a", "b", "c", "free"],
        free_label=3,
        mask="none",
        dynamic_classes=["a"],
        static_classes=["b", "c"],
    )
    g = torch.tensor([0, 0, 1, 1, 3, 3, 2, 3]).reshape(1, 2, 2, 2)
    p = torch.tensor([0, 1, 1, 1, 3, 0, 3, 3]).reshape(1, 2, 2, 2)
    custom.update(p, make_batch(g))
    out = custom.compute()
    assert math.isclose(out["mIoU_dynamic"].item(), 100 / 3, rel_tol=1e-5)
    assert math.isclose(out["mIoU_static"].item(), 100 / 3, rel_tol=1e-5)  # (2/3 + 0) / 2
    plain = Occ3DMIoU(num_classes=4, free_label=3, mask="none")
    plain.update(p, make_batch(g))
    assert "mIoU_dynamic" not in plain.compute()
    with pytest.raises(ValueError, match="unknown class 'x'"):
        Occ3DMIoU(
            num_classes=4,
            class_names=["a", "b", "c", "free"],
            free_label=3,
            dynamic_classes=["x"],
            static_classes=["a"],
        )


def test_excluded_classes_leave_the_means_and_nothing_else():
    from occplug.data.classes import OCC3D_CLASSES

    # the voxels of test_dynamic_and_static_miou_by_hand: others 0, car 1/3, pedestrian 1, driveable 1/2, vegetation 1/2
    gt = torch.tensor([0, 4, 4, 7, 11, 11, 16, 17]).reshape(1, 2, 2, 2)
    pred = torch.tensor([4, 4, 17, 7, 11, 16, 16, 17]).reshape(1, 2, 2, 2)
    m = Occ3DMIoU(class_names=OCC3D_CLASSES, mask="none", exclude_classes=["others", "car", "traffic_cone"])
    m.update(pred, make_batch(gt))
    res = m.compute()
    assert math.isclose(res["mIoU_excl"].item(), 100 * (1 + 0.5 + 0.5) / 3, rel_tol=1e-5)
    assert math.isclose(res["mIoU_dynamic_excl"].item(), 100.0, rel_tol=1e-5)  # pedestrian only
    assert math.isclose(res["mIoU_static_excl"].item(), 50.0, rel_tol=1e-5)
    # the same NaN-means recomputed from the per-class keys without the excluded classes
    kept = [n for n in OCC3D_CLASSES[:17] if n not in ("others", "car", "traffic_cone")]
    per_class = torch.tensor([res[f"IoU_{n}"].item() for n in kept])
    assert math.isclose(res["mIoU_excl"].item(), torch.nanmean(per_class).item(), rel_tol=1e-5)
    plain = Occ3DMIoU(class_names=OCC3D_CLASSES, mask="none")
    plain.update(pred, make_batch(gt))
    base = plain.compute()
    for key, value in base.items():  # the other keys unchanged
        torch.testing.assert_close(res[key], value, equal_nan=True)
    assert not any(k.endswith("_excl") for k in base) and "excl." not in plain.table()
    table = m.table()
    assert "without others, car, traffic_cone:" in table
    assert f"{'mIoU dynamic excl.':<24}{100.0:>8.2f}" in table


def test_unknown_excluded_class_is_an_error_naming_the_valid_ones():
    with pytest.raises(
        ValueError, match=r"occ3d_miou.exclude_classes: unknown class 'cone' \(semantic classes: a, b, c\)"
    ):
        Occ3DMIoU(num_classes=4, class_names=["a", "b", "c", "free"], free_label=3, exclude_classes=["cone"])
