"""``occplug eval --split``: ground truth outside the split is skipped, a missing prediction inside it is an
error, and a sample whose split cannot be told is one line suggesting ``--splits`` or ``--split all``."""

import json
import shutil

import pytest
import torch

from occplug.cli import main
from occplug.data.formats import write_prediction
from occplug.data.nuscenes import format as occ3d
from occplug.data.nuscenes.index import official_splits
from occplug.data.semantickitti import format as kitti

SHAPE = (4, 4, 2)
OFFICIAL = official_splits("v1.0-trainval")
TRAIN_SCENE, VAL_SCENE = sorted(OFFICIAL["train"])[0], sorted(OFFICIAL["val"])[0]


def labels(seed):
    gen = torch.Generator().manual_seed(seed)
    return torch.randint(0, 18, SHAPE, generator=gen, dtype=torch.uint8)


def write_gt(root, scene, token, seed):
    path = root / token / "labels.npz" if scene is None else root / "gts" / scene / token / "labels.npz"
    ones = torch.ones(SHAPE, dtype=torch.bool)
    occ3d.write_labels(path, labels(seed), ones, ones)


def predict(pred_dir, token, seed, wrong=False):
    target = labels(seed).long()
    write_prediction(pred_dir / f"{token}.npz", torch.roll(target, 1, 0) if wrong else target)


def run(gt, pred, *extra, json_out=None):
    out = [] if json_out is None else ["--json", str(json_out)]
    return main(["eval", "--gt", str(gt), "--pred", str(pred), *extra, *out])


def one_error(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0][len("error: ") :]


@pytest.fixture
def occ3d_tree(tmp_path):
    """An official train scene (one sample) and val scene (two samples); predictions of all three,
    the train one and the second val one wrong."""
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    write_gt(gt, TRAIN_SCENE, "t-train", 0)
    write_gt(gt, VAL_SCENE, "t-val-1", 1)
    write_gt(gt, VAL_SCENE, "t-val-2", 2)
    predict(pred, "t-train", 0, wrong=True)
    predict(pred, "t-val-1", 1)
    predict(pred, "t-val-2", 2, wrong=True)
    return gt, pred


def test_occ3d_val_split_scores_only_the_val_scenes(occ3d_tree, tmp_path, capsys):
    gt, pred = occ3d_tree
    assert run(gt, pred, json_out=tmp_path / "val.json") == 0  # default: --split val
    assert "evaluated 2 samples of the val split" in capsys.readouterr().out
    val = json.loads((tmp_path / "val.json").read_text())
    # the reference: the same predictions on a tree holding the val scene only, every sample scored
    only_val = tmp_path / "only_val"
    shutil.copytree(gt / "gts" / VAL_SCENE, only_val / "gts" / VAL_SCENE)
    assert run(only_val, pred, "--split", "all", json_out=tmp_path / "ref.json") == 2  # the train prediction is extra
    assert "t-train.npz has no ground truth" in one_error(capsys)
    (pred / "t-train.npz").rename(tmp_path / "t-train.npz")
    assert run(only_val, pred, "--split", "all", json_out=tmp_path / "ref.json") == 0
    ref = json.loads((tmp_path / "ref.json").read_text())
    assert val["samples"] == ref["samples"] == 2 and val["split"] == "val" and ref["split"] == "all"
    assert val["metrics"] == ref["metrics"] and 0 < val["metrics"]["miou"]["mIoU"] < 100
    # inside the split a missing prediction is an error; outside it, none is needed
    assert run(gt, pred, "--split", "train") == 2
    line = one_error(capsys)
    assert line.startswith("no prediction for token t-train of the train split") and "1 of 1 samples" in line
    assert run(gt, pred, "--split", "all") == 2
    assert "no prediction for token t-train (" in one_error(capsys)
    (pred / "t-val-2.npz").unlink()
    assert run(gt, pred) == 2
    line = one_error(capsys)
    assert line.startswith("no prediction for token t-val-2 of the val split") and "1 of 2 samples affected" in line
    assert run(gt, pred, "--split", "test") == 2
    assert one_error(capsys) == (
        f"--gt {gt}: none of its 3 samples is in the test split of the official nuScenes v1.0-trainval / v1.0-test "
        "split; pick another --split (train, val, test, all) or pass --splits FILE"
    )


def test_occ3d_scenes_of_no_list_need_a_split_file(occ3d_tree, tmp_path, capsys):
    gt, pred = occ3d_tree
    write_gt(gt, "synth-val-0000", "s-val", 3)
    write_gt(gt, "synth-train-0000", "s-train", 4)
    predict(pred, "s-val", 3)
    assert run(gt, pred) == 2
    assert one_error(capsys) == (
        "--split val: cannot tell the split of token s-train (scene folder synth-train-0000 is in no split of the "
        "official nuScenes v1.0-trainval / v1.0-test split); pass --splits FILE (a JSON {split: [names]}) or "
        "--split all (2 of 5 samples affected)"
    )
    split_file = tmp_path / "splits.json"
    # the file replaces the official lists: the official val scene is put in train here
    split_file.write_text(json.dumps({"train": [TRAIN_SCENE, VAL_SCENE, "synth-train-0000"], "val": ["synth-val-0000"]}))
    assert run(gt, pred, "--splits", str(split_file), json_out=tmp_path / "file.json") == 0
    assert json.loads((tmp_path / "file.json").read_text())["samples"] == 1
    # the split record data synth writes beside its tree is read as --splits
    shutil.copy(split_file, gt / "splits.json")
    assert run(gt, pred, json_out=tmp_path / "record.json") == 0
    assert json.loads((tmp_path / "record.json").read_text()) == {
        **json.loads((tmp_path / "file.json").read_text()),
        "gt": str(gt),
    }
    assert run(gt, pred, "--splits", str(tmp_path / "nowhere.json")) == 2
    assert one_error(capsys) == f"{tmp_path / 'nowhere.json'}: no such split file"
    assert run(gt, pred, "--split", "all", "--splits", str(split_file)) == 2
    assert "--splits places samples in splits; it needs --split train, val or test" in one_error(capsys)


def test_occ3d_flat_layout_has_no_scene(tmp_path, capsys):
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    write_gt(gt, None, "flat-1", 1)
    predict(pred, "flat-1", 1)
    assert run(gt, pred) == 2
    line = one_error(capsys)
    assert line == (
        "--split val: cannot tell the split of token flat-1 (the flat <token>/labels.npz layout names no scene); "
        "pass --index DIR or --split all (1 of 1 samples affected)"
    )
    assert run(gt, pred, "--split", "all") == 0


def test_semantickitti_sequences_per_split(tmp_path, capsys):
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    shape = (8, 8, 4)
    for seq, seed in (("00", 0), ("08", 1)):
        gen = torch.Generator().manual_seed(seed)
        raw = torch.tensor([0, 10, 40, 50, 70])[torch.randint(0, 5, shape, generator=gen)]
        label = gt / "sequences" / seq / "voxels" / "000000.label"
        kitti.write_raw_labels(label, raw)
        kitti.write_bits(label.with_suffix(".invalid"), torch.zeros(shape, dtype=torch.bool))
        if seq == "08":
            write_prediction(pred / f"{seq}_000000.npz", kitti.remap_labels(raw).long())
    grid = ["--grid", "0", "-0.8", "-0.4", "1.6", "0.8", "0.4", "--voxel-size", "0.2"]
    assert run(gt, pred, *grid, json_out=tmp_path / "val.json") == 0  # 08 is val; 00 (train) skipped
    res = json.loads((tmp_path / "val.json").read_text())
    assert res["samples"] == 1 and res["metrics"]["ssc"]["IoU"] == 100 and res["metrics"]["ssc"]["IoU_road"] == 100
    assert run(gt, pred, *grid, "--split", "train") == 2
    assert one_error(capsys).startswith("no prediction for token 00_000000 of the train split")
    split_file = tmp_path / "kitti.json"
    split_file.write_text(json.dumps({"val": ["00"]}))  # replaces the standard val split (08 is then in none)
    assert run(gt, pred, *grid, "--splits", str(split_file)) == 2
    assert one_error(capsys).startswith(
        f"--split val: cannot tell the split of token 08_000000 (sequence 08 is in no split of {split_file})"
    )
