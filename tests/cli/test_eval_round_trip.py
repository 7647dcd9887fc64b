"""The newcomer's path on trees written by ``occplug data synth`` (both layouts): ``fit`` -> ``predict`` ->
``occplug eval --gt <the whole tree> --split val`` reproduces what ``validate`` reports, key for key (mIoU,
IoU, every per-class value; RayIoU from the index's origins on Occ3D)."""

import json

import pytest

from occplug.cli import main
from occplug.data.synthetic import preset
from occplug.data.synthetic.export_semantickitti import lidar_grid

TINY = preset("tiny")
KITTI_GRID = lidar_grid(TINY)


def synth(root, fmt, *knobs):
    assert main(["data", "synth", "--format", fmt, "--preset", "tiny", "--out", str(root), "train_scenes=1", *knobs]) == 0


def fit_validate_predict(tmp_path, data_config, grid, *overrides):
    """A few training steps on the tree, then ``validate`` (every val batch) and ``predict``; returns
    ``(validate's metrics, the predictions folder)``."""
    run = tmp_path / "run"
    args = [
        "-c",
        "configs/baseline.yaml",
        "-c",
        "occplug/trainer/debug",
        "-c",
        data_config,
        "data.image_size=null",
        "data.num_workers=0",
        f"grid.range={list(grid.range)}",
        f"grid.voxel_size={grid.voxel_size[0]}",
        *overrides,
    ]
    assert main(["fit", *args, "trainer.limit_val_batches=0", "--run-dir", str(run)]) == 0  # validated below
    ckpt = str(run / "checkpoints" / "last.ckpt")
    every_batch = "trainer.limit_val_batches=1.0"
    assert main(["validate", "--ckpt", ckpt, every_batch, "--json", str(tmp_path / "validate.json")]) == 0
    assert main(["predict", "--ckpt", ckpt, "--out", str(tmp_path / "preds")]) == 0
    return json.loads((tmp_path / "validate.json").read_text()), tmp_path / "preds"


def assert_same(validated, evaluated, metrics):
    """Every value ``eval`` reports equals ``validate``'s (NaN, written as null, included)."""
    scores = {k: v for name in metrics for k, v in evaluated["metrics"][name].items()}
    assert len(scores) > 20
    assert {k: validated[k] for k in scores} == scores


def test_occ3d_tree_round_trip(tmp_path):
    tree = tmp_path / "tree"
    synth(tree, "occ3d")  # train, val and test scenes: eval must skip all but val
    assert (
        main(
            [
                "data",
                "prepare",
                "nuscenes",
                "--root",
                str(tree),
                "--version",
                "v1.0-trainval",
                "--occ",
                str(tree),
                "--out",
                str(tree / "index"),
                "--splits",
                str(tree / "splits.json"),
                "--sweeps",
                "0",
            ]
        )
        == 0
    )
    validated, preds = fit_validate_predict(
        tmp_path, "occplug/data/occ3d_nuscenes", TINY.grid, f"data.root={tree}", f"data.index={tree / 'index'}"
    )
    grid = ["--grid", *map(str, TINY.grid.range), "--voxel-size", str(TINY.grid.voxel_size[0])]
    common = ["eval", "--gt", str(tree), "--pred", str(preds), *grid, "--mask", validated["eval_mask"]]
    out = tmp_path / "eval.json"
    index = ["--index", str(tree / "index")]
    assert main([*common, "--metric", "miou", "rayiou", "--split", "val", *index, "--json", str(out)]) == 0
    evaluated = json.loads(out.read_text())
    assert evaluated["samples"] == len(list(preds.glob("*.npz"))) == 2 and evaluated["split"] == "val"
    assert_same(validated, evaluated, ("miou", "rayiou"))
    assert validated["IoU"] > 0
    # without --index, the split record data synth wrote beside the tree places the scenes
    assert main([*common, "--json", str(out)]) == 0
    assert json.loads(out.read_text())["metrics"]["miou"] == evaluated["metrics"]["miou"]


def test_semantickitti_tree_round_trip(tmp_path, capsys):
    tree = tmp_path / "tree"
    synth(tree, "semantickitti", f"grid={{range: {list(KITTI_GRID.range)}, voxel_size: {KITTI_GRID.voxel_size[0]}}}")
    validated, preds = fit_validate_predict(
        tmp_path,
        "occplug/data/semantickitti",
        KITTI_GRID,
        f"data.root={tree}",
        "model.supervision.voxel_labels.camera_mask=false",
    )
    grid = ["--grid", *map(str, KITTI_GRID.range), "--voxel-size", str(KITTI_GRID.voxel_size[0])]
    out = tmp_path / "eval.json"
    assert main(["eval", "--gt", str(tree), "--pred", str(preds), "--split", "val", *grid, "--json", str(out)]) == 0
    evaluated = json.loads(out.read_text())
    assert evaluated["samples"] == len(list(preds.glob("*.npz"))) == 2 and evaluated["split"] == "val"
    assert_same(validated, evaluated, ("ssc",))
    assert validated["IoU"] > 0
    # the train sequence has ground truth but no prediction: scoring it is the error of a missing prediction
    capsys.readouterr()
    assert main(["eval", "--gt", str(tree), "--pred", str(preds), "--split", "train", *grid]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: no prediction for token 00_000000 of the train split") and "\n" not in err


@pytest.fixture(autouse=True)
def _in_repo_root(monkeypatch):
    """``configs/baseline.yaml`` is a path relative to the repository root."""
    from pathlib import Path

    monkeypatch.chdir(Path(__file__).resolve().parents[2])
