"""End to end: synthetic world -> nuScenes-shaped tree (occplug data synth --format occ3d) -> prepare nuscenes ->
the Occ3D-nuScenes reader gives back the generated frames; bad inputs fail in one line; the baseline trains on it."""

import json
import math
import shutil

import numpy as np
import pytest
import torch

from occplug.cli import main
from occplug.data.formats import FormatError
from occplug.data.nuscenes.index import INDEX_NAME, matrix_to_quaternion, quaternion_to_matrix, read_index
from occplug.data.nuscenes.reader import Occ3DNuScenesDataModule
from occplug.data.sequences import relative_motion
from occplug.data.synthetic import SyntheticDataset, default_cache_dir, preset
from occplug.geometry import invert_pose

TINY = preset("tiny")
GRID = TINY.grid.to_dict()


def prepare(tree, *extra):
    return main(
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
            *extra,
        ]
    )


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    root = tmp_path_factory.mktemp("nuscenes") / "tree"
    assert (
        main(
            [
                "data",
                "synth",
                "--format",
                "occ3d",
                "--preset",
                "tiny",
                "--splits",
                "train",
                "val",
                "--pseudo",
                "default",
                "--out",
                str(root),
                "train_scenes=1",
            ]
        )
        == 0
    )
    assert prepare(root, "--sweeps", "2") == 0
    return root


@pytest.fixture
def copy(tree, tmp_path):
    out = tmp_path / "tree"
    shutil.copytree(tree, out, ignore=shutil.ignore_patterns("index"))
    return out


def module(tree, **kw):
    return Occ3DNuScenesDataModule(root=str(tree), index=str(tree / "index"), grid=GRID, **kw)


def wrap(a):
    return a - 2 * math.pi * torch.floor((a + math.pi) / (2 * math.pi))


def test_frames_read_back_equal_the_generated_ones(tree):
    dm = module(tree)
    index = read_index(tree / "index")
    instances = {
        r["token"]: r["nbr_annotations"] for r in json.loads((tree / "v1.0-trainval" / "instance.json").read_text())
    }
    for split in ("train", "val"):
        ds, gen = dm.dataset(split), SyntheticDataset(TINY, split, cache_dir=default_cache_dir())
        assert len(ds) == TINY.frames(split)
        tracks = {}
        for i in range(len(ds)):
            a, g = ds[i], gen[i]
            assert (a.token, a.scene, a.frame_index, a.timestamp, a.camera_names) == (
                g.token,
                g.scene,
                g.frame_index,
                g.timestamp,
                g.camera_names,
            )
            assert a.extras["is_sequence_start"] == (g.frame_index == 0)
            for name in (
                "images",
                "intrinsics",
                "voxel_labels",
                "mask_camera",
                "mask_lidar",
                "point_labels",
                "box_labels",
            ):
                x, y = getattr(a, name), getattr(g, name)
                assert x.dtype == y.dtype and torch.equal(x, y), name  # lossless PNG, exact labels
            assert torch.equal(a.img_aug, g.img_aug)
            assert torch.allclose(a.cam_to_ego, g.cam_to_ego, atol=1e-5)
            assert torch.allclose(a.lidar_to_ego, g.lidar_to_ego, atol=1e-6)
            assert a.ego_to_global.dtype == torch.float64 and torch.allclose(
                a.ego_to_global, g.ego_to_global, atol=1e-7
            )
            assert torch.equal(a.points[:, :3], g.points[:, :3]) and torch.allclose(
                a.points[:, 3], g.points[:, 3], atol=1e-6
            )
            assert torch.allclose(a.sequence_lidar_origins, g.sequence_lidar_origins, atol=1e-4)
            assert torch.allclose(a.boxes[:, :6], g.boxes[:, :6], atol=1e-4)
            assert torch.allclose(wrap(a.boxes[:, 6] - g.boxes[:, 6]), torch.zeros(len(a.boxes)), atol=1e-5)
            several = torch.tensor([instances[index.meta["instances"][t]] > 1 for t in a.box_track_ids.tolist()])
            assert several.any()
            assert torch.allclose(a.boxes[several, 7:], g.boxes[several, 7:], atol=1e-4)  # devkit velocities
            for ours, theirs in zip(a.box_track_ids.tolist(), g.box_track_ids.tolist(), strict=True):
                assert tracks.setdefault((a.scene, theirs), ours) == ours  # track ids: a consistent renaming
        assert len(set(tracks.values())) == len(tracks)


def test_adjacent_frames_sweeps_and_sequential_loading(tree):
    dm = module(tree, adjacent_offsets=[-1, 1], num_sweeps=2, sequential=True)
    ds = dm.dataset("train")
    first, mid = ds[0], ds[1]
    assert first.adjacent[-1].token == first.token and first.adjacent[1].token == mid.token  # clamped at the start
    gen = SyntheticDataset(TINY, "train", cache_dir=default_cache_dir())
    expected = invert_pose(gen[1].ego_to_global) @ gen[0].ego_to_global
    assert torch.allclose(relative_motion(mid, -1), expected, atol=1e-6)
    # the previous sweep, motion-compensated into this LiDAR frame, with its time lag
    lag = mid.extras["point_time_lag"]
    assert len(lag) == len(mid.points) == len(mid.point_labels) and set(lag.unique().tolist()) == {0.0, 0.5}
    prev_in_cur = gen[0].points_in_ego().double() @ expected[:3, :3].T + expected[:3, 3]
    swept = mid.points[lag > 0, :3].double() @ mid.lidar_to_ego[:3, :3].T.double() + mid.lidar_to_ego[:3, 3]
    assert torch.allclose(swept, prev_in_cur, atol=1e-3)
    starts = [b.is_sequence_start.tolist() for b in dm.train_dataloader()]
    assert starts == [[True], [False], [False]]


def test_points_are_not_opened_when_not_needed(copy):
    shutil.rmtree(copy / "samples" / "LIDAR_TOP")
    assert prepare(copy, "--no-check-files") == 0
    f = Occ3DNuScenesDataModule(root=str(copy), index=str(copy / "index"), grid=GRID, load_points=False).dataset("val")[
        0
    ]
    assert f.points is None and f.voxel_labels is not None


def _lidar(paths):
    return [p for p in paths if "LIDAR_TOP" in p or "lidarseg" in p]


def test_camera_only_runs_never_open_lidar_files(copy, touched):
    assert prepare(copy, "--sweeps", "2") == 0
    # control: a LiDAR-reading model opens them (so the spy sees LiDAR paths when they are opened)
    dm = module(copy, num_sweeps=2)
    dm.require_fields({"points", "point_labels"})
    assert dm.dataset("val")[1].points is not None and _lidar(touched)
    # every LIDAR_TOP file (keyframes, which are also the sweeps of this tree) and every lidarseg file removed
    index = read_index(copy / "index")
    assert any(rec["sweeps"] for rec in index.samples)
    shutil.rmtree(copy / "samples" / "LIDAR_TOP")
    shutil.rmtree(copy / "lidarseg")
    touched.clear()
    dm = module(copy, num_sweeps=2)  # load_points auto: construction stats no LiDAR file
    dm.require_fields(set())
    read = 0
    for split in ("train", "val", "test", "predict"):
        ds = dm.dataset(split)
        for i in range(len(ds)):
            f = ds[i]
            assert f.points is None and f.point_labels is None and f.voxel_labels is not None and f.images.shape[0] == 6
            read += 1
    assert read == 2 * TINY.frames("val") + TINY.frames("train")
    assert touched and not _lidar(touched)
    # a LiDAR-supervised model: one line naming the first missing file (the first training sample's keyframe)
    first = copy / index.samples[index.split_indices("train")[0]]["lidar"]
    with pytest.raises(FormatError, match=rf"^{first}: no such file$"):
        module(copy).require_fields({"points"})
    with pytest.raises(FormatError, match=rf"^{first}: no such file$"):
        module(copy).require_fields({"point_labels"})
    with pytest.raises(ValueError, match=r"data\.load_points is false but the model reads LiDAR points \(points\)"):
        module(copy, load_points=False).require_fields({"points", "mask_camera"})
    # an explicit load_points false stays camera-only when undeclared too
    assert module(copy, load_points=False).dataset("val")[0].points is None


def test_sweeps_are_checked_when_used(copy, capsys):
    """A sweep (a non-keyframe LiDAR sample_data in the ``prev`` chain) that is missing: ``prepare`` names it, and a
    reader with ``num_sweeps > 1`` names it at construction (keyframe-only readers do not need it)."""
    folder = copy / "v1.0-trainval"
    rows = json.loads((folder / "sample_data.json").read_text())
    key = next(r for r in rows if r["is_key_frame"] and "LIDAR_TOP" in r["filename"] and r["prev"])
    sweep = dict(
        key,
        token="extra-sweep",
        is_key_frame=False,
        next=key["token"],
        sample_token=key["sample_token"],
        filename="sweeps/LIDAR_TOP/extra-sweep.pcd.bin",
        timestamp=key["timestamp"] - 50_000,
    )
    next(r for r in rows if r["token"] == key["prev"])["next"] = sweep["token"]
    key["prev"] = sweep["token"]
    (folder / "sample_data.json").write_text(json.dumps([*rows, sweep]))
    missing = copy / sweep["filename"]
    capsys.readouterr()
    assert prepare(copy, "--sweeps", "2") == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"error: {missing}: missing LiDAR sweep (of sample {key['sample_token']}; --sweeps 0 records none)"
    )
    assert not (copy / "index" / INDEX_NAME).exists()
    assert prepare(copy, "--sweeps", "2", "--no-check-files") == 0
    with pytest.raises(FormatError, match=rf"^{missing}: no such file$"):
        module(copy, num_sweeps=2, load_points=True)
    with pytest.raises(FormatError, match=rf"^{missing}: no such file$"):
        module(copy, num_sweeps=2).require_fields({"points"})
    module(copy, num_sweeps=1, load_points=True)  # the keyframes alone are complete
    missing.parent.mkdir(parents=True)
    missing.write_bytes(b"\0" * 30)  # 1.5 points
    with pytest.raises(FormatError, match=rf"^{missing}: 30 bytes is not a whole number of 5-float32 points"):
        module(copy, num_sweeps=2, load_points=True)


def test_a_wrong_shape_met_after_the_first_label_file_fails_in_one_line_when_read(copy):
    assert prepare(copy) == 0
    index = read_index(copy / "index")
    items = index.split_indices("val")
    victim = copy / index.samples[items[1]]["occ"]
    good = np.load(victim)
    np.savez_compressed(
        victim,
        semantics=good["semantics"][:, :, :4],
        mask_lidar=good["mask_lidar"][:, :, :4],
        mask_camera=good["mask_camera"][:, :, :4],
    )
    ds = module(copy).dataset("val")  # construction checks only the first labels.npz of a split: cheap
    assert ds[0].voxel_labels.shape == TINY.grid.shape
    with pytest.raises(FormatError, match=rf"^{victim}: 'semantics' has shape \(40, 40, 4\); expected \(40, 40, 8\)$"):
        ds[1]


@pytest.mark.parametrize("workers", [0, 1])
def test_a_bad_label_file_met_during_fit_is_one_line_from_the_cli(copy, tmp_path, capsys, workers):
    """Also from inside a loader worker, whose exception arrives wrapped with the worker's traceback."""
    assert prepare(copy) == 0
    index = read_index(copy / "index")
    victim = copy / index.samples[index.split_indices("val")[1]]["occ"]
    good = np.load(victim)
    np.savez_compressed(
        victim,
        semantics=good["semantics"][:, :, :4],
        mask_lidar=good["mask_lidar"][:, :, :4],
        mask_camera=good["mask_camera"][:, :, :4],
    )
    capsys.readouterr()
    code = main(
        [
            "fit",
            "-c",
            "configs/baseline.yaml",
            "-c",
            "occplug/trainer/debug",
            "-c",
            "occplug/data/occ3d_nuscenes",
            f"data.root={copy}",
            f"data.index={copy / 'index'}",
            "data.image_size=null",
            f"data.num_workers={workers}",
            f"grid.range={list(TINY.grid.range)}",
            f"grid.voxel_size={TINY.grid.voxel_size[0]}",
            "metrics=[occ3d_miou]",
            "--run-dir",
            str(tmp_path / "run"),
        ]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err == f"error: {victim}: 'semantics' has shape (40, 40, 4); expected (40, 40, 8)"


def test_pseudo_labels_from_the_tree(tree):
    p = tree / "pseudo"
    primary = {"dir": str(p / "semantics"), "mapping": str(p / "semantics_mapping.yaml")}
    auxiliary = {"dir": str(p / "semantics_aux"), "mapping": str(p / "semantics_aux_mapping.yaml")}
    dm = module(
        tree,
        pseudo_labels={"depth": str(p / "depth"), "features": str(p / "features"), "semantics": [primary, auxiliary]},
        image_size=[24, 48],
    )
    f = dm.dataset("val")[0]
    assert f.pseudo_depth.shape == (6, 24, 48) and f.pseudo_semantics.shape == (6, 24, 48)
    # the tree's two sources merged as the on-the-fly labeler merges them
    from occplug.data.synthetic.pseudo import SyntheticPseudoLabels

    made = SyntheticPseudoLabels("default").attach(SyntheticDataset(TINY, "val", cache_dir=default_cache_dir())[0])
    raw = module(tree, pseudo_labels={"semantics": [primary, auxiliary]}).dataset("val")[0]
    assert torch.equal(raw.pseudo_semantics, made.pseudo_semantics)
    assert f.pseudo_features.shape[:2] == (6, 16)


@pytest.mark.parametrize("damage", ["missing_table", "missing_labels", "corrupt_bin", "no_split"])
def test_bad_trees_fail_in_one_line_naming_the_file_and_leave_no_index(copy, damage, capsys):
    extra = []
    if damage == "missing_table":
        (copy / "v1.0-trainval" / "sample_annotation.json").unlink()
        expected = "v1.0-trainval/sample_annotation.json: missing nuScenes table 'sample_annotation'"
    elif damage == "missing_labels":
        victim = sorted((copy / "gts").rglob("labels.npz"))[1]
        victim.unlink()
        expected = f"{victim}: missing Occ3D labels.npz"
    elif damage == "corrupt_bin":
        victim = sorted((copy / "samples" / "LIDAR_TOP").iterdir())[-1]
        victim.write_bytes(victim.read_bytes()[:-6])
        expected = f"{victim}: "
    else:
        (copy / "splits.json").write_text(json.dumps({"train": ["synth-train-0000"]}))
        expected = "synth-val-0000 are in no split"
    capsys.readouterr()
    assert prepare(copy, *extra) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: ") and expected in err[-1], err
    assert not (copy / "index" / INDEX_NAME).exists() and not list((copy).glob("index/*"))


def test_bad_inputs_at_construction_are_one_line_errors(copy, capsys):
    assert prepare(copy) == 0
    # wrong grid shape: the labels are 40 x 40 x 8, the default grid is Occ3D's 200 x 200 x 16
    with pytest.raises(
        FormatError, match=r"labels\.npz: 'semantics' has shape \(40, 40, 8\); expected \(200, 200, 16\)"
    ):
        Occ3DNuScenesDataModule(root=str(copy), index=str(copy / "index"))
    bad_map = copy / "pseudo" / "bad.yaml"
    bad_map.write_text((copy / "pseudo" / "semantics_mapping.yaml").read_text().replace("pedestrian", "pedestrain"))
    with pytest.raises(FormatError, match=r"bad\.yaml: map\.person: unknown target class 'pedestrain'"):
        module(copy, pseudo_labels={"semantics": {"dir": str(copy / "pseudo" / "semantics"), "mapping": str(bad_map)}})
    with pytest.raises(FormatError, match="no nuScenes index"):
        Occ3DNuScenesDataModule(root=str(copy), index=str(copy / "nowhere"))
    # through the CLI: one line, exit 2, no run directory
    capsys.readouterr()
    run = copy.parent / "run"
    fit = [
        "fit",
        "--run-dir",
        str(run),
        "-c",
        "configs/baseline.yaml",
        "-c",
        "occplug/trainer/debug",
        "-c",
        "occplug/data/occ3d_nuscenes",
        f"data.root={copy}",
        f"data.index={copy / 'index'}",
    ]
    assert main(fit) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "labels.npz: 'semantics' has shape" in err[0]
    # a LiDAR file cut short after the index was built: found at construction with load_points true, and
    # with auto (the default) once the model declares that it reads points
    victim = sorted((copy / "samples" / "LIDAR_TOP").iterdir())[0]
    victim.write_bytes(victim.read_bytes()[:-4])
    with pytest.raises(FormatError, match="not a whole number of 5-float32 points"):
        module(copy, load_points=True)
    dm = module(copy)
    with pytest.raises(FormatError, match=f"{victim}: .* not a whole number of 5-float32 points"):
        dm.require_fields({"points"})
    assert main([*fit, f"grid.range={list(TINY.grid.range)}", "grid.voxel_size=0.8", "data.load_points=true"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"error: {victim}: " in err[0]
    assert not run.exists()


def test_baseline_trains_on_the_tree_with_only_the_data_node_switched(tree, tmp_path, capsys):
    """``occplug/configs/data/occ3d_nuscenes.yaml`` switches data (and the grid to Occ3D's); the tiny tree's
    labels are 40 x 40 x 8 at 0.8 m, so its grid is set back, as a user of a smaller tree would."""
    run = tmp_path / "run"
    args = [
        "fit",
        "-c",
        "configs/baseline.yaml",
        "-c",
        "occplug/trainer/debug",
        "-c",
        "occplug/data/occ3d_nuscenes",
        f"data.root={tree}",
        f"data.index={tree / 'index'}",
        "data.image_size=null",
        "data.num_workers=0",
        f"grid.range={list(TINY.grid.range)}",
        f"grid.voxel_size={TINY.grid.voxel_size[0]}",
        "--run-dir",
        str(run),
    ]
    assert main(args) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["global_step"] == 2 and metrics["IoU"] == metrics["IoU"]
    saved = (run / "config.yaml").read_text()
    assert "type: occ3d_nuscenes" in saved


def test_quaternions_round_trip():
    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        q = torch.randn(4, generator=g, dtype=torch.float64)
        q = (q / q.norm() * (1 if q[0] >= 0 else -1)).numpy()
        r = quaternion_to_matrix(q)
        assert np.allclose(r @ r.T, np.eye(3)) and np.isclose(np.linalg.det(r), 1)
        assert np.allclose(matrix_to_quaternion(r), q)


def test_decoded_frame_cache_gives_identical_frames(tree, tmp_path):
    plain = module(tree, num_sweeps=2).dataset("val")
    cached = module(tree, num_sweeps=2, cache_dir=str(tmp_path)).dataset("val")
    for _ in range(2):  # the second pass reads the cache
        a, b = plain[1], cached[1]
        for name in ("images", "points", "point_labels", "voxel_labels", "mask_camera", "boxes", "cam_to_ego"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name
        assert torch.equal(a.extras["point_time_lag"], b.extras["point_time_lag"])
    assert len(list(tmp_path.rglob("*.pt"))) == 1


def test_camera_only_runs_need_no_lidar_file_and_lidar_supervision_names_the_missing_one(copy, tmp_path, capsys):
    """With every LIDAR_TOP file (keyframes and sweeps) and lidarseg file gone, the camera-only baseline
    trains, validates and predicts; adding LiDAR depth supervision fails in one line naming the first missing file."""
    assert prepare(copy, "--sweeps", "2") == 0  # the index of the complete tree
    removed = [p for p in copy.rglob("*") if p.is_file() and ("LIDAR_TOP" in p.name or "lidarseg" in p.parts)]
    assert len(removed) > 5
    for path in removed:
        path.unlink()
    common = [
        "-c",
        "configs/baseline.yaml",
        "-c",
        "occplug/trainer/debug",
        "-c",
        "occplug/data/occ3d_nuscenes",
        f"data.root={copy}",
        f"data.index={copy / 'index'}",
        "data.image_size=null",
        "data.num_workers=0",
        f"grid.range={list(TINY.grid.range)}",
        f"grid.voxel_size={TINY.grid.voxel_size[0]}",
    ]
    run = tmp_path / "camera_only"
    assert main(["fit", *common, "--run-dir", str(run)]) == 0
    assert json.loads((run / "metrics.json").read_text())["global_step"] == 2
    ckpt = str(run / "checkpoints" / "last.ckpt")
    assert main(["validate", "--ckpt", ckpt]) == 0
    assert main(["predict", "--ckpt", ckpt, "--out", str(tmp_path / "preds")]) == 0
    capsys.readouterr()

    lidar_run = tmp_path / "lidar"
    assert main(["fit", *common, "model.supervision.depth={type: lidar_depth}", "--run-dir", str(lidar_run)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "LIDAR_TOP" in err and err.endswith(".pcd.bin: no such file"), err
    assert not lidar_run.exists()  # nothing written half-way


def test_eval_takes_rayiou_origins_from_the_prepared_index(tree, tmp_path, capsys):
    """``occplug eval --index`` casts from the same sequence origins the reader gives each frame."""
    from occplug.data.nuscenes.format import find_label_files

    labels = find_label_files(tree)
    dm = module(tree)
    frames = {
        f.token: f for split in ("train", "val") for f in (dm.dataset(split)[i] for i in range(len(dm.dataset(split))))
    }
    assert set(labels) == set(frames)
    preds = tmp_path / "preds"
    preds.mkdir()
    for token, frame in frames.items():
        wrong = frame.voxel_labels.clone()
        wrong[:, :, :2] = 4  # the two lowest layers all car: errors that depend on where rays start
        np.savez(preds / f"{token}.npz", pred=wrong.numpy())
    np.savez(tmp_path / "origins.npz", **{t: f.sequence_lidar_origins.double().numpy() for t, f in frames.items()})
    grid = ["--grid", *map(str, TINY.grid.range), "--voxel-size", str(TINY.grid.voxel_size[0])]
    common = ["eval", "--gt", str(tree), "--pred", str(preds), "--metric", "rayiou", *grid]

    assert main([*common, "--index", str(tree / "index"), "--json", str(tmp_path / "index.json")]) == 0
    assert "notice" not in capsys.readouterr().err
    assert main([*common, "--origins", str(tmp_path / "origins.npz"), "--json", str(tmp_path / "file.json")]) == 0
    by_index = json.loads((tmp_path / "index.json").read_text())["metrics"]["rayiou"]
    by_file = json.loads((tmp_path / "file.json").read_text())["metrics"]["rayiou"]
    assert by_index == pytest.approx(by_file, abs=1e-3)
    capsys.readouterr()
    assert main([*common, "--json", str(tmp_path / "one.json")]) == 0
    assert "notice: RayIoU casts from one fixed origin per sample" in capsys.readouterr().err
    single = json.loads((tmp_path / "one.json").read_text())["metrics"]["rayiou"]
    assert single["RayIoU"] != pytest.approx(by_index["RayIoU"], abs=1e-3)


def test_rayiou_origin_of_the_sample_is_its_calibration_exactly_and_face_rays_start_on_its_side(tree):
    """The LiDAR sits at y = 0, a voxel face of the grid: the sample's own origin must be the calibration
    translation exactly (a pose round trip leaves y at about +-1e-14, and a ray in the plane y = 0 then
    starts in the row below the face, as it does for sample 3 of this tree with the old arithmetic)."""
    from occplug.data.classes import OCC3D_CLASSES, OCC3D_FREE
    from occplug.metrics import cast_query_rays, query_ray_directions

    index = read_index(tree / "index")
    ego, lidar = index.arrays["ego_to_global"], index.arrays["lidar_to_ego"]
    grid = TINY.grid
    face_row = grid.shape[1] // 2  # y in [0, voxel): the side the floor rule selects for y = 0
    assert grid.lower[1] + face_row * grid.voxel_size[1] == 0.0
    directions = query_ray_directions()
    in_face = directions[:, 1] == 0  # azimuth 0: the rays lying in the plane y = 0
    assert int(in_face.sum()) == 39
    car = OCC3D_CLASSES.index("car")
    labels = torch.full(grid.shape, OCC3D_FREE, dtype=torch.int64)
    labels[:, face_row] = car  # only the row on the +y side of the face is occupied
    frames = {f.token: f for split in ("train", "val") for f in module(tree).dataset(split)}
    for s, record in enumerate(index.samples):
        members = index.scene_members()[record["scene"]]
        origins = index.sequence_lidar_origins(s)
        own = origins[members.index(s)]
        assert own.tolist() == lidar[s, :3, 3].tolist() and own[1] == 0.0, s
        assert frames[record["token"]].sequence_lidar_origins[members.index(s)].tolist() == own.tolist()
        for row, j in zip(origins, members, strict=True):  # every frame: the composition to 1e-12 m
            r_s, r_j = ego[s, :3, :3].astype(np.longdouble), ego[j, :3, :3].astype(np.longdouble)
            exact = r_s.T @ (r_j @ lidar[j, :3, 3] + ego[j, :3, 3] - ego[s, :3, 3])
            assert np.abs(row - exact.astype(np.float64)).max() < 1e-12, (s, j)
        rays = cast_query_rays(labels, labels, grid, torch.from_numpy(own)[None], OCC3D_FREE, directions)
        assert (rays.gt_class[in_face] == car).all(), f"sample {s}: rays in the face plane missed the +y row"
