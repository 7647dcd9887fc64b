"""``occplug data check``: a correct synthetic tree passes; each kind of damage exits 2 with one line naming the
first offending file (or scene) and how many files share the problem; the tree is never changed."""

import contextlib
import hashlib
import io
import json
import shlex
import shutil

import numpy as np
import pytest

from occplug.cli import main
from occplug.data.synthetic import preset
from occplug.data.synthetic.export_semantickitti import lidar_grid

TINY = preset("tiny")
SHAPE = [str(v) for v in TINY.grid.shape]  # the tiny world's Occ3D-layout labels: 40 x 40 x 8
KITTI_GRID = lidar_grid(TINY)
KITTI_SHAPE = [str(v) for v in KITTI_GRID.shape]
PRINTED: dict = {}  # {tree: what data synth printed when writing it}


def synth(root, *args):
    """``occplug data synth`` into ``root``; what it prints is kept in :data:`PRINTED`."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["data", "synth", "--out", str(root), *args]) == 0
    PRINTED[root] = out.getvalue()


@pytest.fixture(scope="module")
def nuscenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("check") / "nuscenes"
    synth(root, "--format", "occ3d", "--preset", "tiny", "train_scenes=1", "--splits", "train", "val")
    return root


@pytest.fixture(scope="module")
def kitti(tmp_path_factory):
    root = tmp_path_factory.mktemp("check") / "kitti"
    grid = f"grid={{range: {list(KITTI_GRID.range)}, voxel_size: {KITTI_GRID.voxel_size[0]}}}"
    synth(root, "--format", "semantickitti", "--preset", "tiny", "train_scenes=1", grid, "--splits", "train", "val")
    return root


def listing(root):
    """Every path under ``root`` with its size, modification time and (files) content hash."""
    out = []
    for p in sorted(root.rglob("*")):
        st = p.stat()
        digest = hashlib.sha1(p.read_bytes()).hexdigest() if p.is_file() else None
        out.append((str(p.relative_to(root)), st.st_size, st.st_mtime_ns, digest))
    return out


def check_ns(tree, *extra):
    """``data check nuscenes`` of a synthetic tree, against the tiny grid (``--shape``) unless ``extra`` gives one."""
    shape = [] if "--shape" in extra or "no-shape" in extra else ["--shape", *SHAPE]
    extra = [e for e in extra if e != "no-shape"]
    return main(
        [
            "data",
            "check",
            "nuscenes",
            "--root",
            str(tree),
            "--version",
            "v1.0-trainval",
            "--occ",
            str(tree),
            "--splits",
            str(tree / "splits.json"),
            *shape,
            *extra,
        ]
    )


def one_error_line(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0][len("error: ") :]


def test_a_correct_nuscenes_tree_passes_and_is_left_unchanged(nuscenes, capsys):
    before = listing(nuscenes)
    capsys.readouterr()
    assert check_ns(nuscenes) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == f"ok: nuScenes tree {nuscenes} (v1.0-trainval; scenes per {nuscenes / 'splits.json'})"
    assert out[1:3] == ["  train: 1 scene, 3 samples", "  val: 1 scene, 2 samples"]
    assert out[3] == (
        "  checked: 30 images, 5 LiDAR files (keyframes and sweeps), 5 lidarseg files, 5 label files (40, 40, 8)"
    )
    assert listing(nuscenes) == before
    # an explicit benchmark grid (Occ3D's): every label file of this tree has another shape
    assert check_ns(nuscenes, "--shape", "200", "200", "16") == 2
    assert "'semantics' has shape (40, 40, 8); expected (200, 200, 16) (5 of 5 label files affected)" in one_error_line(
        capsys
    )
    # the official split: the tree's scenes are in none of its lists (as prepare says)
    assert main(["data", "check", "nuscenes", "--root", str(nuscenes), "--version", "v1.0-trainval"]) == 2
    assert "synth-train-0000, synth-val-0000 are in no split of the official v1.0-trainval split" in one_error_line(
        capsys
    )
    assert listing(nuscenes) == before


@pytest.mark.parametrize(
    "damage", ["removed_labels", "wrong_shape", "truncated_lidar", "missing_image", "missing_scene", "no_lidar"]
)
def test_each_damage_exits_2_naming_the_file_and_writes_nothing(nuscenes, tmp_path, damage, capsys):
    tree = tmp_path / "tree"
    shutil.copytree(nuscenes, tree)
    gts = sorted((tree / "gts").rglob("labels.npz"))
    if damage == "removed_labels":  # the whole val scene's labels: 2 files
        shutil.rmtree(tree / "gts" / "synth-val-0000")
        victim = [p for p in gts if "synth-val-0000" in str(p)][0]
        expected = f"{victim}: no such file (2 of 5 label files affected)"
    elif damage == "wrong_shape":
        victim = gts[2]
        good = np.load(victim)
        np.savez_compressed(
            victim,
            semantics=good["semantics"][:, :, :4],
            mask_lidar=good["mask_lidar"],
            mask_camera=good["mask_camera"],
        )
        expected = f"{victim}: 'semantics' has shape (40, 40, 4); expected (40, 40, 8) (1 of 5 label files affected)"
    elif damage == "truncated_lidar":
        victim = sorted((tree / "samples" / "LIDAR_TOP").iterdir())[1]
        data = victim.read_bytes()[:-6]
        victim.write_bytes(data)
        expected = (
            f"{victim}: {len(data)} bytes is not a whole number of 5-float32 points (corrupt .bin?) "
            "(1 of 5 LiDAR files affected)"
        )
    elif damage == "missing_image":
        victim = sorted((tree / "samples" / "CAM_BACK").iterdir())[-1]
        victim.unlink()
        expected = f"{victim}: no such file (1 of 30 images affected)"
    elif damage == "missing_scene":
        tables = tree / "v1.0-trainval" / "scene.json"
        tables.write_text(json.dumps([s for s in json.loads(tables.read_text()) if s["name"] != "synth-val-0000"]))
        expected = (
            f"{tables}: scene synth-val-0000 of the val split is missing "
            f"(1 of 2 scenes of {tree / 'splits.json'} affected)"
        )
    else:  # every LiDAR file gone: a LiDAR check fails, a camera-only check (--no-lidar) passes
        shutil.rmtree(tree / "samples" / "LIDAR_TOP")
        shutil.rmtree(tree / "lidarseg")
        victim = tree / "samples" / "LIDAR_TOP"
        expected = f"{victim}/synth-train-0000__LIDAR_TOP__"
    before = listing(tree)
    capsys.readouterr()
    assert check_ns(tree) == 2
    line = one_error_line(capsys)
    assert line.startswith(expected) if damage == "no_lidar" else line == expected, line
    if damage == "no_lidar":
        assert (
            "no such file (5 of 5 LiDAR files affected); also " in line
            and "_lidarseg.bin: no such file (5 of 5 lidarseg files)" in line
        )
        assert check_ns(tree, "--no-lidar") == 0
        assert "LiDAR files not checked (--no-lidar)" in capsys.readouterr().out
    assert listing(tree) == before


def test_index_check(nuscenes, tmp_path, capsys):
    tree = tmp_path / "tree"
    shutil.copytree(nuscenes, tree)
    index = tmp_path / "index"
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
                str(index),
                "--splits",
                str(tree / "splits.json"),
                "--sweeps",
                "2",
            ]
        )
        == 0
    )
    check = ["data", "check", "index", "--index", str(index), "--splits", str(tree / "splits.json"), "--shape", *SHAPE]
    capsys.readouterr()
    assert main(check) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == f"ok: index {index / 'nuscenes_index.npz'} (root {tree}; scenes per {tree / 'splits.json'})"
    assert out[1:3] == ["  train: 1 scene, 3 samples", "  val: 1 scene, 2 samples"]
    assert main(check[:-4]) == 0  # no --shape: the grid record of the Occ3D folder the index names
    assert f"  grid (40, 40, 8) from {tree / 'grid.json'}" in capsys.readouterr().out.splitlines()
    assert main([*check[:-4], "--shape", "200", "200", "16"]) == 2
    assert "expected (200, 200, 16) (5 of 5 label files affected)" in one_error_line(capsys)
    # files the index names vanish: every CAM_FRONT image, and one label file
    shutil.rmtree(tree / "samples" / "CAM_FRONT")
    label = sorted((tree / "gts").rglob("labels.npz"))[3]
    label.unlink()
    before, before_index = listing(tree), listing(index)
    assert main(check) == 2
    line = one_error_line(capsys)
    assert line.startswith(f"{tree / 'samples' / 'CAM_FRONT' / 'synth-train-0000__CAM_FRONT__'}")
    assert (
        "no such file (5 of 30 images affected); also " in line
        and f"{label}: no such file (1 of 5 label files)" in line
    )
    # an index checked against a split it was not built for: every scene of the reference is named as missing
    assert main(["data", "check", "index", "--index", str(index), "--shape", *SHAPE, "--no-lidar"]) == 2
    assert one_error_line(capsys).startswith(
        f"{index / 'nuscenes_index.npz'}: scene scene-0001 of the train split is "
        "missing (850 of 850 scenes of the official v1.0-trainval split affected)"
    )
    assert main(["data", "check", "index", "--index", str(tmp_path / "nowhere")]) == 2
    assert "no nuScenes index" in one_error_line(capsys)
    assert listing(tree) == before and listing(index) == before_index


@pytest.fixture
def kitti_split(tmp_path):
    path = tmp_path / "split.json"  # outside the tree: the synthetic tree holds sequences 00 (train) and 08 (val)
    path.write_text(json.dumps({"train": ["00"], "val": ["08"]}))
    return path


def check_kitti(tree, split, *extra):
    return main(
        ["data", "check", "semantickitti", "--root", str(tree), "--splits", str(split), "--shape", *KITTI_SHAPE, *extra]
    )


def test_a_correct_semantickitti_tree_passes(kitti, kitti_split, capsys):
    before = listing(kitti)
    capsys.readouterr()
    assert check_kitti(kitti, kitti_split) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[1:3] == ["  train: 1 sequence, 3 samples", "  val: 1 sequence, 2 samples"]
    assert out[3] == (f"  checked: 5 images, 20 voxel files {KITTI_GRID.shape}, 5 velodyne files, 5 point-label files")
    # against the standard split, sequences 01-07, 09 and 10 are missing
    assert main(["data", "check", "semantickitti", "--root", str(kitti), "--shape", *KITTI_SHAPE]) == 2
    assert one_error_line(capsys) == (
        f"{kitti / 'sequences' / '01'}: no such train sequence folder "
        "(9 of 11 sequences of the standard split affected)"
    )
    assert listing(kitti) == before


@pytest.mark.parametrize("damage", ["voxel_bin", "invalid", "image", "velodyne", "voxel_label", "sequence"])
def test_each_semantickitti_damage_exits_2_naming_the_file(kitti, kitti_split, tmp_path, damage, capsys):
    tree = tmp_path / "tree"
    shutil.copytree(kitti, tree)
    seq = tree / "sequences" / "00"
    count = int(np.prod(KITTI_GRID.shape))
    if damage in ("voxel_bin", "invalid"):
        victim = seq / "voxels" / f"000005.{damage.replace('voxel_', '')}"
        victim.write_bytes(victim.read_bytes()[:-3])
        expected = f"{victim}: {count // 8 - 3} bytes; expected {count // 8} ({count} voxels, 8 per byte) (1 of 20 voxel files affected)"
    elif damage == "image":
        victim = tree / "sequences" / "08" / "image_2" / "000005.png"
        victim.unlink()
        expected = f"{victim}: no such file (1 of 5 images affected)"
    elif damage == "velodyne":
        victim = seq / "velodyne" / "000010.bin"
        data = victim.read_bytes()[:-4]
        victim.write_bytes(data)
        expected = f"{victim}: {len(data)} bytes is not a whole number of 4-float32 points (corrupt .bin?) (1 of 5 velodyne files affected)"
    elif damage == "voxel_label":  # the scan's .bin/.invalid/.occluded remain: its .label is named
        victim = seq / "voxels" / "000010.label"
        victim.unlink()
        expected = f"{victim}: no such file (1 of 20 voxel files affected)"
    else:
        shutil.rmtree(tree / "sequences" / "08")
        victim = tree / "sequences" / "08"
        expected = f"{victim}: no such val sequence folder (1 of 2 sequences of {kitti_split} affected)"
    before = listing(tree)
    capsys.readouterr()
    assert check_kitti(tree, kitti_split) == 2
    assert one_error_line(capsys) == expected
    assert listing(tree) == before


def test_progress_bar_shows_once_a_check_runs_long(nuscenes, monkeypatch, capsys):
    from occplug.data import check

    monkeypatch.setattr(check, "PROGRESS_DELAY", 0.0)  # as if the tree were large: the bar shows at once
    capsys.readouterr()
    assert check_ns(nuscenes) == 0
    err = capsys.readouterr().err
    assert "nuScenes index: " in err and "data check: " in err and "sample/s" in err
    assert check_ns(nuscenes, "--no-progress") == 0
    assert capsys.readouterr().err == ""


# ----------------------------------------------------------------------------------------------
# the grid a check expects: --shape, else the tree's grid record, else what the label files share


@pytest.mark.parametrize("layout", ["nuscenes", "kitti"])
def test_synth_prints_the_check_command_and_it_passes_without_shape(layout, request, capsys):
    tree = request.getfixturevalue(layout)
    record = json.loads((tree / "grid.json").read_text())
    grid = TINY.grid if layout == "nuscenes" else KITTI_GRID
    assert record == {"shape": list(grid.shape), "range": list(grid.range), "voxel_size": list(grid.voxel_size)}
    lines = [line for line in PRINTED[tree].splitlines() if line.startswith("check it with: ")]
    assert len(lines) == 1
    command = shlex.split(lines[0][len("check it with: ") :])
    name = "nuscenes" if layout == "nuscenes" else "semantickitti"
    tail = ["--version", "v1.0-trainval", "--occ", str(tree)] if layout == "nuscenes" else []
    assert command == ["occplug", "data", "check", name, "--root", str(tree), *tail, "--splits", f"{tree}/splits.json"]
    before = listing(tree)
    capsys.readouterr()
    assert main(command[1:]) == 0
    out = capsys.readouterr().out.splitlines()
    files = "label files" if layout == "nuscenes" else "voxel files"
    assert f"{files} {grid.shape}" in out[3] and f"  grid {grid.shape} from {tree / 'grid.json'}" in out
    # an explicit --shape is still the check against a benchmark's grid
    wrong = ["--shape", "200", "200", "16"]
    assert main([*command[1:], *wrong]) == 2
    line = one_error_line(capsys)
    assert (
        ("expected (200, 200, 16) (5 of 5 label files affected)" in line)
        if layout == "nuscenes"
        else ("(640000 uint16 voxels of a (200, 200, 16) grid)" in line or "expected 80000 (640000 voxels" in line)
    ), line
    assert listing(tree) == before


def test_without_a_record_the_shape_most_label_files_share_is_expected(nuscenes, tmp_path, capsys):
    tree = tmp_path / "tree"
    shutil.copytree(nuscenes, tree)
    (tree / "grid.json").unlink()
    capsys.readouterr()
    assert check_ns(tree, "no-shape") == 0
    out = capsys.readouterr().out.splitlines()
    assert out[3].endswith("5 label files (40, 40, 8)")
    assert "  grid (40, 40, 8): the shape most label files share (no --shape, no grid record)" in out
    victim = sorted((tree / "gts").rglob("labels.npz"))[1]
    good = np.load(victim)
    np.savez_compressed(
        victim,
        semantics=good["semantics"][:, :, :4],
        mask_lidar=good["mask_lidar"][:, :, :4],
        mask_camera=good["mask_camera"][:, :, :4],
    )
    before = listing(tree)
    assert check_ns(tree, "no-shape") == 2
    assert one_error_line(capsys) == (
        f"{victim}: 'semantics' has shape (40, 40, 4); expected (40, 40, 8), the shape most label files share "
        "(1 of 5 label files affected)"
    )
    assert listing(tree) == before
    # with the record back, the same file is reported against the recorded grid
    shutil.copy(nuscenes / "grid.json", tree / "grid.json")
    assert check_ns(tree, "no-shape") == 2
    assert one_error_line(capsys) == (
        f"{victim}: 'semantics' has shape (40, 40, 4); expected (40, 40, 8) (1 of 5 label files affected)"
    )
    (tree / "grid.json").write_text("{not json")
    assert check_ns(tree, "no-shape") == 2
    assert one_error_line(capsys) == (
        f'{tree / "grid.json"}: not a grid record; expected {{"shape": [X, Y, Z], ...}} (positive integers)'
    )


def test_a_semantickitti_tree_without_a_record_is_checked_against_the_ssc_grid(kitti, kitti_split, tmp_path, capsys):
    tree = tmp_path / "tree"
    shutil.copytree(kitti, tree)
    (tree / "grid.json").unlink()
    capsys.readouterr()
    assert main(["data", "check", "semantickitti", "--root", str(tree), "--splits", str(kitti_split)]) == 2
    count, voxels = 256 * 256 * 32, tree / "sequences" / "00" / "voxels"
    tiny = int(np.prod(KITTI_GRID.shape))
    assert one_error_line(capsys) == (
        f"{voxels / '000000.bin'}: {tiny // 8} bytes; expected {count // 8} ({count} voxels, 8 per byte) "
        f"(15 of 20 voxel files affected); also {voxels / '000000.label'}: {2 * tiny} bytes; expected {2 * count} "
        f"({count} uint16 voxels of a (256, 256, 32) grid) (5 of 20 voxel files)"
    )
    assert check_kitti(tree, kitti_split) == 0  # told the grid, it passes


def test_prepare_refuses_a_split_naming_a_missing_scene_as_check_does(nuscenes, tmp_path, capsys):
    """A ``--splits`` file naming a scene the tables lack: ``data check`` and ``data prepare`` both exit 2 with the
    same line, and prepare writes no index."""
    splits = json.loads((nuscenes / "splits.json").read_text())
    splits["val"] = [*splits["val"], "synth-val-0099"]
    split_file = tmp_path / "splits.json"
    split_file.write_text(json.dumps(splits))
    expected = (
        f"{nuscenes / 'v1.0-trainval' / 'scene.json'}: scene synth-val-0099 of the val split is missing "
        f"(1 of {sum(map(len, splits.values()))} scenes of {split_file} affected)"
    )
    capsys.readouterr()
    assert check_ns(nuscenes, "--splits", str(split_file)) == 2
    assert one_error_line(capsys) == expected
    out = tmp_path / "index"
    prepare = ["data", "prepare", "nuscenes", "--root", str(nuscenes), "--version", "v1.0-trainval"]
    assert main([*prepare, "--occ", str(nuscenes), "--out", str(out), "--splits", str(split_file)]) == 2
    assert one_error_line(capsys) == expected
    assert not (out / "nuscenes_index.npz").exists()
