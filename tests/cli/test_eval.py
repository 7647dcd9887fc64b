"""``occplug eval`` and the on-disk formats it reads (Occ3D labels.npz, SemanticKITTI voxels, predictions)."""

import json
import math
import re

import numpy as np
import pytest
import torch

from occplug.cli import main
from occplug.data.classes import OCC3D_CLASSES, SEMANTIC_KITTI_LEARNING_MAP, SEMANTIC_KITTI_LEARNING_MAP_INV
from occplug.data.formats import FormatError, read_prediction, write_prediction
from occplug.data.frame import Batch
from occplug.data.nuscenes import format as occ3d
from occplug.data.semantickitti import format as kitti
from occplug.geometry import GridSpec
from occplug.metrics import Occ3DMIoU, RayIoU, SSCMetrics
from occplug.testing.fixtures import make_tiny_batch

# ----------------------------------------------------------------------------------------------
# Formats


def test_occ3d_labels_round_trip_as_occ3d_stores_them(tmp_path):
    gen = torch.Generator().manual_seed(0)
    sem = torch.randint(0, 18, (6, 5, 4), generator=gen).to(torch.uint8)
    lidar, camera = torch.rand(2, 6, 5, 4, generator=gen) < 0.5
    path = tmp_path / "gts" / "scene-1" / "tok" / "labels.npz"
    occ3d.write_labels(path, sem, lidar, camera)
    with np.load(path) as raw:
        assert raw["semantics"].dtype == np.uint8 and raw["mask_camera"].dtype == np.uint8
    labels = occ3d.read_labels(path, expected_shape=(6, 5, 4))
    assert torch.equal(labels.semantics, sem) and labels.semantics.dtype == torch.uint8
    assert torch.equal(labels.mask_lidar, lidar) and torch.equal(labels.mask_camera, camera)
    assert occ3d.find_label_files(tmp_path) == {"tok": path}
    assert occ3d.find_label_files(tmp_path / "gts") == {"tok": path}


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"mask_camera": None}, "missing key 'mask_camera'"),
        (
            {"semantics": np.zeros((200, 200, 8), np.uint8)},
            "'semantics' has shape (200, 200, 8); expected (200, 200, 16)",
        ),
        ({"semantics": np.zeros((200, 200, 16), np.float32)}, "'semantics' has dtype float32; expected uint8"),
        ({"mask_camera": np.zeros((200, 200, 16), np.int64)}, "'mask_camera' has dtype int64; expected uint8 or bool"),
        ({"mask_lidar": np.full((200, 200, 16), 2, np.uint8)}, "'mask_lidar' holds values other than 0 and 1"),
        ({"mask_lidar": np.zeros((200, 200, 15), np.uint8)}, "'mask_lidar' has shape (200, 200, 15)"),
    ],
)
def test_occ3d_reader_errors_name_the_file(tmp_path, changes, message):
    arrays = {key: np.zeros((200, 200, 16), np.uint8) for key in ("semantics", "mask_lidar", "mask_camera")}
    arrays.update(changes)
    path = tmp_path / "labels.npz"
    np.savez(path, **{k: v for k, v in arrays.items() if v is not None})
    with pytest.raises(FormatError) as info:
        occ3d.read_labels(path)
    assert str(info.value).startswith(f"{path}: ") and message in str(info.value) and "\n" not in str(info.value)


def test_occ3d_layouts_and_duplicate_tokens(tmp_path):
    sem = np.zeros((2, 2, 2), np.uint8)
    for token in ("a", "b"):
        occ3d.write_labels(tmp_path / "flat" / token / "labels.npz", sem, sem, sem)
    assert sorted(occ3d.find_label_files(tmp_path / "flat")) == ["a", "b"]
    occ3d.write_labels(tmp_path / "dup" / "s1" / "a" / "labels.npz", sem, sem, sem)
    occ3d.write_labels(tmp_path / "dup" / "s2" / "a" / "labels.npz", sem, sem, sem)
    with pytest.raises(FormatError, match="token a also appears"):
        occ3d.find_label_files(tmp_path / "dup")
    assert occ3d.find_label_files(tmp_path / "nothing") == {}


def test_semantickitti_bit_packing_matches_unpackbits_order(tmp_path):
    bits = np.zeros(16, dtype=bool)
    bits[[0, 7, 9]] = True  # voxel 0 is the most significant bit of byte 0
    assert kitti.pack(bits).tolist() == [0b10000001, 0b01000000]
    grid = torch.rand(8, 6, 4, generator=torch.Generator().manual_seed(1)) < 0.3
    assert torch.equal(kitti.unpack(kitti.pack(grid), (8, 6, 4)), grid)
    kitti.write_bits(tmp_path / "x.invalid", grid)
    assert (tmp_path / "x.invalid").stat().st_size == 8 * 6 * 4 // 8
    assert torch.equal(kitti.read_bits(tmp_path / "x.invalid", (8, 6, 4)), grid)
    with pytest.raises(FormatError, match=r"x\.invalid: 24 bytes; expected 262144$"):
        kitti.read_bits(tmp_path / "x.invalid")  # the full 256 x 256 x 32 grid needs 262,144 bytes
    with pytest.raises(FormatError, match="no such file"):
        kitti.read_bits(tmp_path / "missing.bin")


def test_semantickitti_labels_learning_map_and_layout(tmp_path):
    lut = kitti.learning_map_lut()
    assert [lut[r] for r in (0, 10, 252, 40, 60, 81, 1, 52, 99, 7, 65535)] == [
        0,
        1,
        1,
        9,
        9,
        19,
        255,
        255,
        255,
        255,
        255,
    ]
    assert kitti.learning_map_lut(completion=False)[52] == 0
    assert all(SEMANTIC_KITTI_LEARNING_MAP[SEMANTIC_KITTI_LEARNING_MAP_INV[c]] == c for c in range(20))
    raw = torch.tensor([0, 10, 252, 52, 81, 71, 99, 40]).reshape(2, 2, 2)
    label = tmp_path / "sequences" / "08" / "voxels" / "000123.label"
    kitti.write_raw_labels(label, raw)
    assert label.stat().st_size == 16 and torch.equal(kitti.read_raw_labels(label, (2, 2, 2)), raw.int())
    kitti.write_bits(
        label.with_suffix(".invalid"), torch.tensor([1, 0, 0, 0, 0, 0, 0, 1], dtype=torch.bool).reshape(2, 2, 2)
    )
    vox = kitti.read_voxels(label, (2, 2, 2))
    assert vox.labels.reshape(-1).tolist() == [0, 1, 1, 255, 19, 16, 255, 9] and vox.invalid.reshape(-1).tolist()[
        ::7
    ] == [True, True]
    assert kitti.find_label_files(tmp_path) == {"08_000123": label} and kitti.sample_token(8, 123) == "08_000123"


def test_prediction_files(tmp_path):
    pred = torch.randint(0, 18, (4, 4, 2))
    write_prediction(tmp_path / "t.npz", pred)
    assert np.load(tmp_path / "t.npz")["pred"].dtype == np.uint8
    assert torch.equal(read_prediction(tmp_path / "t.npz", (4, 4, 2)), pred)
    np.savez(tmp_path / "i.npz", pred=pred.numpy().astype(np.int64))  # an external model's int64 ids read too
    assert torch.equal(read_prediction(tmp_path / "i.npz"), pred)
    np.savez(tmp_path / "f.npz", pred=pred.numpy().astype(np.float32))
    np.savez(tmp_path / "k.npz", semantics=pred.numpy())
    for name, message in (
        ("f", "dtype float32"),
        ("k", "no 'pred' array (keys: semantics)"),
        ("t", "expected (4, 4, 3)"),
    ):
        with pytest.raises(FormatError, match=re.escape(f"{tmp_path / name}.npz: ") + ".*" + re.escape(message)):
            read_prediction(tmp_path / f"{name}.npz", (4, 4, 3))


# ----------------------------------------------------------------------------------------------
# occplug eval on a ground-truth tree written from the synthetic world

TINY_GRID = ["--grid", "-16", "-16", "-1", "16", "16", "5.4", "--voxel-size", "0.8"]  # the tiny world's grid


@pytest.fixture
def occ3d_tree(tmp_path):
    """gts/<scene>/<token>/labels.npz of two tiny synthetic val frames (40 x 40 x 8 at 0.8 m), their
    origins file, and predictions: the first perfect, the second shifted one voxel along x."""
    batch = make_tiny_batch(2, "val")
    gt, pred_dir = tmp_path / "gt", tmp_path / "pred"
    preds = []
    for b, token in enumerate(batch.token):
        occ3d.write_labels(
            gt / "gts" / batch.scene[b] / token / "labels.npz",
            batch.voxel_labels[b],
            batch.mask_lidar[b],
            batch.mask_camera[b],
        )
        pred = batch.voxel_labels[b] if b == 0 else torch.roll(batch.voxel_labels[b], 1, 0)
        write_prediction(pred_dir / f"{token}.npz", pred)
        preds.append(pred.long())
    np.savez(
        tmp_path / "origins.npz",
        **{t: o.numpy() for t, o in zip(batch.token, batch.sequence_lidar_origins, strict=True)},
    )
    return gt, pred_dir, tmp_path / "origins.npz", batch, torch.stack(preds)


def labels_batch(labels, **fields):
    b = labels.shape[0]
    return Batch(
        images=torch.zeros(b, 0, 3, 1, 1),
        intrinsics=torch.zeros(b, 0, 3, 3),
        cam_to_ego=torch.zeros(b, 0, 4, 4),
        img_aug=torch.zeros(b, 0, 3, 3),
        ego_to_global=torch.eye(4, dtype=torch.float64).expand(b, 4, 4),
        timestamp=torch.zeros(b, dtype=torch.float64),
        frame_index=torch.zeros(b, dtype=torch.int64),
        has_voxel_labels=torch.ones(b, dtype=torch.bool),
        is_sequence_start=torch.ones(b, dtype=torch.bool),
        scene=["s"] * b,
        token=[str(i) for i in range(b)],
        voxel_labels=labels,
        **fields,
    )


def run_eval(gt, pred, *extra):
    """These hand-built trees record no split: every sample is scored (``--split all``) unless told otherwise."""
    split = [] if "--split" in extra else ["--split", "all"]
    return main(["eval", "--gt", str(gt), "--pred", str(pred), *split, *extra])


def test_eval_equals_the_metrics_on_the_same_batch(occ3d_tree, tmp_path, capsys):
    gt, pred, origins, batch, preds = occ3d_tree
    out = tmp_path / "scores.json"
    assert (
        run_eval(
            gt, pred, "--metric", "miou", "rayiou", "ssc", "--origins", str(origins), *TINY_GRID, "--json", str(out)
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert (
        "Occ3D mIoU (evaluation mask: camera)" in printed
        and "RayIoU (SparseOcc" in printed
        and "SemanticKITTI SSC" in printed
    )
    assert "evaluated 2 samples" in printed
    summary = next(line for line in printed.splitlines() if line.startswith("evaluated 2 samples"))
    # RayIoU's group and class-agnostic means are headline values, its per-class values are not
    assert "RayIoU_geometry=" in summary and "RayIoU_dynamic=" in summary and "RayIoU_car=" not in summary
    scores = json.loads(out.read_text())
    assert scores["samples"] == 2 and set(scores["metrics"]) == {"miou", "rayiou", "ssc"}
    grid = GridSpec((-16, -16, -1, 16, 16, 5.4), 0.8)
    expected = {
        "miou": Occ3DMIoU(class_names=OCC3D_CLASSES),
        "rayiou": RayIoU(class_names=OCC3D_CLASSES, grid=grid),
        "ssc": SSCMetrics(num_classes=18, class_names=OCC3D_CLASSES, free_label=17),
    }
    for name, metric in expected.items():
        metric.update(preds, batch)
        for key, value in metric.compute().items():
            got = scores["metrics"][name][key]
            assert (got is None and math.isnan(value)) or got == pytest.approx(float(value), abs=1e-4), (name, key)
    assert 0 < scores["metrics"]["rayiou"]["RayIoU_1m"] < scores["metrics"]["rayiou"]["RayIoU_4m"] < 100


def test_eval_perfect_predictions_and_single_origin_fallback(occ3d_tree, tmp_path):
    gt, _, _, batch, _ = occ3d_tree
    perfect = tmp_path / "perfect"
    for b, token in enumerate(batch.token):
        write_prediction(perfect / f"{token}.npz", batch.voxel_labels[b])
    out = tmp_path / "s.json"
    assert (
        run_eval(
            gt, perfect, "--metric", "miou", "rayiou", *TINY_GRID, "--origin", "0.9", "0", "1.8", "--json", str(out)
        )
        == 0
    )
    res = json.loads(out.read_text())["metrics"]
    assert res["miou"]["mIoU"] == 100 and res["rayiou"]["RayIoU"] == 100


def expect_error(capsys, *parts):
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    for part in parts:
        assert part in err, err


def test_missing_extra_and_mismatched_files_exit_2_and_write_nothing(occ3d_tree, tmp_path, capsys):
    gt, pred, origins, batch, _ = occ3d_tree
    out = tmp_path / "never.json"
    first, second = batch.token
    (pred / f"{second}.npz").rename(tmp_path / "aside.npz")
    assert run_eval(gt, pred, "--json", str(out)) == 2
    expect_error(capsys, f"no prediction for token {second}", "1 of 2 samples affected")
    (tmp_path / "aside.npz").rename(pred / f"{second}.npz")
    write_prediction(pred / "stray.npz", torch.zeros(2, 2, 2))
    assert run_eval(gt, pred, "--json", str(out)) == 2
    expect_error(capsys, "stray.npz has no ground truth", "1 predictions affected")
    (pred / "stray.npz").unlink()
    for token in batch.token:  # both predictions on the wrong grid
        write_prediction(pred / f"{token}.npz", torch.zeros(40, 40, 4))
    assert run_eval(gt, pred, "--json", str(out)) == 2
    expect_error(capsys, f"token {first}:", "has shape (40, 40, 4); expected (40, 40, 8)", "2 of 2 samples affected")
    assert not out.exists()


def test_broken_ground_truth_origins_and_grid_errors(occ3d_tree, tmp_path, capsys):
    gt, pred, origins, batch, _ = occ3d_tree
    second = batch.token[1]
    bad = next(gt.rglob(f"{second}/labels.npz"))
    np.savez(bad, semantics=np.zeros((40, 40, 8), np.uint8))
    assert run_eval(gt, pred) == 2
    expect_error(capsys, f"token {second}: {bad}: missing key 'mask_lidar'", "1 of 2 samples affected")
    occ3d.write_labels(bad, batch.voxel_labels[1], batch.mask_lidar[1], batch.mask_camera[1])
    assert run_eval(gt, pred, "--metric", "rayiou") == 2  # 40 x 40 x 8 labels, default Occ3D grid
    expect_error(capsys, "do not match the RayIoU grid's (200, 200, 16); pass --grid/--voxel-size", "2 of 2")
    np.savez(tmp_path / "few.npz", **{batch.token[0]: np.zeros((3, 3))})
    assert run_eval(gt, pred, "--metric", "rayiou", "--origins", str(tmp_path / "few.npz"), *TINY_GRID) == 2
    expect_error(capsys, f"no origins for token {second}", "1 of 2 samples affected")
    assert run_eval(tmp_path / "nowhere", pred) == 2
    expect_error(capsys, "not a folder")
    assert run_eval(gt, pred, "--metric", "ssc", "--mask", "lidar") == 2
    expect_error(capsys, "--mask applies to --metric miou only")


def test_eval_semantickitti_layout(tmp_path, capsys):
    shape = (8, 8, 4)
    gen = torch.Generator().manual_seed(3)
    raw_ids = torch.tensor([0, 0, 0, 10, 40, 48, 50, 70, 52])  # 52: ignored
    classes = kitti.remap_labels(raw_ids).long()
    pred_dir = tmp_path / "pred"
    preds, targets, invalids = [], [], []
    for frame in range(2):
        raw = raw_ids[torch.randint(0, len(raw_ids), shape, generator=gen)]
        invalid = torch.rand(shape, generator=gen) < 0.1
        label = tmp_path / "gt" / "sequences" / "08" / "voxels" / f"{frame:06d}.label"
        kitti.write_raw_labels(label, raw)
        kitti.write_bits(label.with_suffix(".invalid"), invalid)
        target = kitti.remap_labels(raw).long()
        pred = torch.where(torch.rand(shape, generator=gen) < 0.8, target.clamp(max=19), classes[3])
        write_prediction(pred_dir / f"08_{frame:06d}.npz", pred)
        preds.append(pred), targets.append(target), invalids.append(invalid)
    grid = ["--grid", "0", "-0.8", "-0.4", "1.6", "0.8", "0.4", "--voxel-size", "0.2"]
    out = tmp_path / "ssc.json"
    assert run_eval(tmp_path / "gt", pred_dir, *grid, "--json", str(out)) == 0
    assert "SemanticKITTI SSC (semantic-kitti-api scorer; empty = empty (0)" in capsys.readouterr().out
    expected = SSCMetrics()
    expected.update(torch.stack(preds), labels_batch(torch.stack(targets), voxel_invalid=torch.stack(invalids)))
    got = json.loads(out.read_text())["metrics"]["ssc"]
    for key, value in expected.compute().items():
        assert got[key] == pytest.approx(float(value), abs=1e-4), key
    assert 0 < got["IoU"] < 100
    assert run_eval(tmp_path / "gt", pred_dir, *grid, "--metric", "miou") == 2
    expect_error(capsys, "miou is the Occ3D metric")


def test_labels_predictions_and_origins_outside_what_can_be_scored(occ3d_tree, tmp_path, capsys):
    """Ground-truth ids outside the taxonomy and non-finite origins are refused in one line naming the file;
    predicted ids outside it are one line for mIoU, while RayIoU scores them as SparseOcc does."""
    gt, pred, origins, batch, preds = occ3d_tree
    first, second = batch.token
    out = tmp_path / "never.json"
    label_file = next(gt.rglob(f"{second}/labels.npz"))
    broken = batch.voxel_labels[1].clone()
    broken[3, 4, 2] = 23
    occ3d.write_labels(label_file, broken, batch.mask_lidar[1], batch.mask_camera[1])
    for metric in ("miou", "rayiou"):
        assert run_eval(gt, pred, "--metric", metric, *TINY_GRID, "--json", str(out)) == 2
        expect_error(capsys, f"token {second}: {label_file}: ground-truth class id 23 is outside the taxonomy")
    occ3d.write_labels(label_file, batch.voxel_labels[1], batch.mask_lidar[1], batch.mask_camera[1])
    car = OCC3D_CLASSES.index("car")
    unknown = torch.where(preds[0] == car, 255, preds[0])
    assert (unknown == 255).any()
    write_prediction(pred / f"{first}.npz", unknown)
    assert run_eval(gt, pred, "--metric", "miou", "rayiou", *TINY_GRID, "--json", str(out)) == 2
    expect_error(capsys, f"token {first}: {pred / (first + '.npz')}: predicted class id 255 is outside 0..17")
    assert not out.exists()
    assert run_eval(gt, pred, "--metric", "rayiou", "--origins", str(origins), *TINY_GRID, "--json", str(out)) == 0
    expected = RayIoU(class_names=OCC3D_CLASSES, grid=GridSpec((-16, -16, -1, 16, 16, 5.4), 0.8))
    expected.update(torch.stack([unknown, preds[1]]), batch)
    got = json.loads(out.read_text())["metrics"]["rayiou"]
    assert got["RayIoU"] == pytest.approx(float(expected.compute()["RayIoU"]), abs=1e-4)
    assert got["RayIoU_car"] < 100 and got["RayIoU_geometry"] > got["RayIoU"]
    out.unlink()
    with np.load(origins) as data:
        arrays = dict(data)
    for bad in (math.nan, math.inf):
        arrays[second] = arrays[second].copy()
        arrays[second][0, 1] = bad
        np.savez(tmp_path / "bad_origins.npz", **arrays)
        assert run_eval(gt, pred, "--metric", "rayiou", "--origins", str(tmp_path / "bad_origins.npz"), *TINY_GRID) == 2
        expect_error(capsys, f"--origins {tmp_path / 'bad_origins.npz'}: token {second} has a non-finite origin")
    assert run_eval(gt, pred, "--metric", "rayiou", "--origin", "0.9", "nan", "1.8", *TINY_GRID) == 2
    expect_error(capsys, "--origin: expected three finite numbers")
    assert not out.exists()
