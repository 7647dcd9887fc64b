"""End to end: synthetic world -> SemanticKITTI-shaped tree (occplug data synth --format semantickitti) -> the
SemanticKITTI reader gives back the generated frames in the velodyne frame, bit packing included."""

import json
import shutil

import numpy as np
import pytest
import torch

from occplug.cli import main
from occplug.data import collate_frames
from occplug.data.classes import OCC3D_TO_SEMANTIC_KITTI as OCC3D_TO_SSC
from occplug.data.formats import FormatError
from occplug.data.semantickitti.format import pack, read_bits, unpack
from occplug.data.semantickitti.reader import SemanticKITTIDataModule
from occplug.data.synthetic import LIDAR_TO_EGO, SyntheticDataset, default_cache_dir, preset
from occplug.data.synthetic.export_semantickitti import lidar_grid, semantickitti_world
from occplug.geometry import invert_pose

TINY = preset("tiny")
GRID = lidar_grid(TINY)  # the tiny world's label grid in the LiDAR frame


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    root = tmp_path_factory.mktemp("kitti") / "tree"
    grid = f"grid={{range: {list(GRID.range)}, voxel_size: {GRID.voxel_size[0]}}}"
    assert semantickitti_world(TINY, GRID).cache_key() == TINY.cache_key()  # the cached tiny frames are reused
    assert (
        main(
            [
                "data",
                "synth",
                "--format",
                "semantickitti",
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
                grid,
            ]
        )
        == 0
    )
    return root


@pytest.fixture
def copy(tree, tmp_path):
    out = tmp_path / "tree"
    shutil.copytree(tree, out)
    return out


def module(root, **kw):
    return SemanticKITTIDataModule(root=str(root), grid=GRID.to_dict(), **kw)


def test_layout_is_semantickitti(tree):
    seq = tree / "sequences"
    assert sorted(p.name for p in seq.iterdir()) == ["00", "08"]  # standard split: train 00, val 08
    assert sorted(p.name for p in (seq / "00" / "voxels").iterdir())[:4] == [
        "000000.bin",
        "000000.invalid",
        "000000.label",
        "000000.occluded",
    ]
    assert sorted(p.stem for p in (seq / "00" / "image_2").iterdir()) == ["000000", "000005", "000010"]
    assert len((seq / "00" / "poses.txt").read_text().splitlines()) == 11  # every scan, 10 Hz
    assert (seq / "00" / "calib.txt").read_text().splitlines()[4].startswith("Tr: ")


def test_frames_read_back_equal_the_generated_ones(tree):
    dm = module(tree)
    lidar = LIDAR_TO_EGO.double()
    ssc = torch.tensor(OCC3D_TO_SSC)
    for split in ("train", "val"):
        ds, gen = dm.dataset(split), SyntheticDataset(TINY, split, cache_dir=default_cache_dir())
        assert len(ds) == TINY.frames(split)
        origin = None
        for i in range(len(ds)):
            a, g = ds[i], gen[i]
            cam = g.cam_to_ego[0].double()
            origin = g.ego_to_global @ cam if g.frame_index == 0 else origin
            assert a.token == f"{a.scene}_{5 * g.frame_index:06d}" and a.extras["scan"] == 5 * g.frame_index
            assert (a.frame_index, a.camera_names) == (g.frame_index, ("image_2",))
            assert abs(a.timestamp - g.timestamp) < 1e-12
            assert torch.equal(a.images[0], g.images[0]) and torch.equal(a.intrinsics[0], g.intrinsics[0])
            # the ego frame is the velodyne frame; the global frame is the sequence's first cam0 frame
            assert torch.equal(a.lidar_to_ego, torch.eye(4))
            assert torch.allclose(a.cam_to_ego[0].double(), invert_pose(lidar) @ cam, atol=1e-5)
            assert torch.allclose(a.ego_to_global, invert_pose(origin) @ g.ego_to_global @ lidar, atol=1e-6)
            assert torch.equal(a.points, g.points)
            assert torch.equal(a.point_labels, ssc[g.point_labels])
            assert a.voxel_labels.dtype == torch.uint8 and torch.equal(
                a.voxel_labels.long(), ssc[g.voxel_labels.long()]
            )
            assert torch.equal(a.voxel_invalid, ~(g.mask_lidar | g.mask_camera))  # through the bit packing
            assert torch.allclose(a.sequence_lidar_origins, g.sequence_lidar_origins - lidar[:3, 3].float(), atol=1e-4)
            assert a.boxes is None and a.mask_camera is None


def test_bit_packing_round_trip(tree):
    rng = np.random.default_rng(0)
    bits = rng.random((16, 8, 4)) < 0.3
    assert torch.equal(unpack(pack(bits), (16, 8, 4)), torch.from_numpy(bits))
    assert pack(np.array([1, 0, 0, 0, 0, 0, 0, 1], bool)).tolist() == [0b10000001]  # most significant bit first
    path = tree / "sequences" / "00" / "voxels" / "000005.invalid"
    assert path.stat().st_size * 8 == int(np.prod(GRID.shape))
    assert read_bits(path, GRID.shape).shape == GRID.shape


def test_loader_with_resize_augmentation_adjacent_frames_and_pseudo_labels(tree):
    p = tree / "pseudo"
    dm = module(
        tree,
        image_size=[24, 48],
        adjacent_offsets=[-1],
        batch_size=2,
        sequential=True,
        augment={"image": {"flip": 0.5}, "bev": {"flip_y": 0.5}},
        pseudo_labels={
            "depth": str(p / "depth"),
            "semantics": {"dir": str(p / "semantics"), "mapping": str(p / "semantics_mapping.yaml")},
        },
    )
    batches = list(dm.train_dataloader())
    b = batches[0]
    assert b.images.shape == (2, 1, 3, 24, 48) and b.pseudo_depth.shape == (2, 1, 24, 48)
    assert b.voxel_invalid.shape == (2, *GRID.shape) and b.adjacent[-1].token == b.token
    assert int(b.pseudo_semantics.max()) <= 255 and int(b.pseudo_semantics[b.pseudo_semantics != 255].max()) < 20
    assert b.is_sequence_start.tolist() == [True, True]  # lane 2 replays the only training sequence


def test_bad_inputs_fail_in_one_line_naming_the_file(copy):
    velo = copy / "sequences" / "08" / "velodyne" / "000005.bin"
    good = velo.read_bytes()
    velo.write_bytes(good[:-8])
    with pytest.raises(
        FormatError, match=r"08/velodyne/000005\.bin: \d+ bytes is not a whole number of 4-float32 points"
    ):
        module(copy, load_points=True)
    dm = module(copy)  # load_points auto: LiDAR files are checked once the model declares points
    with pytest.raises(
        FormatError, match=r"08/velodyne/000005\.bin: \d+ bytes is not a whole number of 4-float32 points"
    ):
        dm.require_fields({"points"})
    velo.write_bytes(good)
    invalid = copy / "sequences" / "00" / "voxels" / "000010.invalid"
    invalid.write_bytes(invalid.read_bytes()[:-1])
    with pytest.raises(FormatError, match=r"000010\.invalid: \d+ bytes; expected \d+ \(\d+ voxels, 8 per byte\)"):
        module(copy)
    with pytest.raises(FormatError, match=r"000000\.label: \d+ bytes; expected"):
        SemanticKITTIDataModule(root=str(copy))  # the default SSC grid (256 x 256 x 32) does not fit this tree
    invalid.unlink()
    with pytest.raises(FormatError, match=r"000010\.invalid: no such file"):
        module(copy)
    (copy / "sequences" / "00" / "calib.txt").write_text("P2: 1 2 3\n")
    with pytest.raises(FormatError, match=r"calib\.txt: 'P2' has 3 numbers; expected 12"):
        module(copy)
    with pytest.raises(ValueError, match="unknown split"):
        module(copy, splits={"training": ["00"]})


def test_splits_argument_replaces_the_standard_split(tree):
    dm = module(tree, splits={"train": ["08"], "val": ["00"]})
    assert dm.dataset("train")[0].scene == "08" and dm.dataset("predict")[0].scene == "00"
    assert collate_frames([dm.dataset("val")[0]]).voxel_labels.shape == (1, *GRID.shape)


def _lidar(paths):
    return [p for p in paths if "/velodyne/" in p or "/labels/" in p]


def test_camera_only_runs_never_open_velodyne_or_point_label_files(copy, touched):
    dm = module(copy)
    dm.require_fields({"points"})
    assert dm.dataset("val")[0].point_labels is not None and _lidar(touched)  # control: the spy sees them
    for seq in ("00", "08"):
        shutil.rmtree(copy / "sequences" / seq / "velodyne")
        shutil.rmtree(copy / "sequences" / seq / "labels")
    touched.clear()
    dm = module(copy)  # load_points auto
    dm.require_fields(set())
    read = 0
    for split in ("train", "val", "predict"):
        ds = dm.dataset(split)
        for i in range(len(ds)):
            f = ds[i]
            assert f.points is None and f.point_labels is None and f.voxel_labels is not None
            read += 1
    assert read == len(dm.dataset("train")) + 2 * len(dm.dataset("val")) > 0
    assert touched and not _lidar(touched)
    first = copy / "sequences" / "00" / "velodyne" / "000000.bin"
    with pytest.raises(FormatError, match=rf"^{first}: no such file$"):
        module(copy).require_fields({"points"})
    for seq in ("00", "08"):  # velodyne back, labels/ still missing: a point-label model names the first .label
        (copy / "sequences" / seq / "velodyne").mkdir()
        for scan in (0, 5, 10):
            (copy / "sequences" / seq / "velodyne" / f"{scan:06d}.bin").write_bytes(b"\0" * 32)
    with pytest.raises(FormatError, match=rf"^{copy / 'sequences' / '00' / 'labels' / '000000.label'}: no such file$"):
        module(copy).require_fields({"point_labels"})
    with pytest.raises(
        ValueError, match=r"data\.load_points is false but the model reads LiDAR points \(point_labels\)"
    ):
        module(copy, load_points=False).require_fields({"point_labels"})


def test_missing_sequences(copy):
    with pytest.raises(
        FormatError,
        match=rf"^{copy / 'sequences' / '05'}: no such sequence folder \(none of the val "
        r"sequences 05, 06 is present\)$",
    ):
        module(copy, splits={"val": ["05", "06"]})
    dm = module(copy, splits={"train": ["00", "03"]})  # partly present: read what is there
    assert dm.dataset("train").missing == ["03"] and {f.scene for f in dm.dataset("train")} == {"00"}
    # the standard test split (11-21) is absent: fine until it is read
    with pytest.raises(FormatError, match=rf"^{copy / 'sequences' / '11'}: no such sequence folder"):
        dm.dataset("test")


def test_decoded_frame_cache_is_not_stale_after_the_tree_is_rewritten(copy, tmp_path):
    cache = tmp_path / "cache"
    before = module(copy, cache_dir=str(cache)).dataset("val")[1]
    assert len(list(cache.rglob("*.pt"))) == 1
    again = module(copy, cache_dir=str(cache)).dataset("val")[1]  # unchanged tree: served from the cache
    assert len(list(cache.rglob("*.pt"))) == 1 and torch.equal(again.voxel_labels, before.voxel_labels)
    label = copy / "sequences" / "08" / "voxels" / f"{before.extras['scan']:06d}.label"
    raw = np.fromfile(label, dtype=np.uint16)
    raw[:] = 40  # every voxel "road" (SSC class 9), rewritten in place with the same size
    raw.tofile(label)
    after = module(copy, cache_dir=str(cache)).dataset("val")[1]
    assert bool((after.voxel_labels == 9).all()) and not torch.equal(after.voxel_labels, before.voxel_labels)
    assert len(list(cache.rglob("*.pt"))) == 2


def test_baseline_trains_on_the_tree_and_reports_ssc_scores(tree, tmp_path, capsys):
    run = tmp_path / "run"
    args = [
        "fit",
        "-c",
        "configs/baseline.yaml",
        "-c",
        "occplug/trainer/debug",
        "-c",
        "occplug/data/semantickitti",
        f"data.root={tree}",
        "data.image_size=null",
        "data.num_workers=0",
        f"grid.range={list(GRID.range)}",
        f"grid.voxel_size={GRID.voxel_size[0]}",
        "model.supervision.voxel_labels.camera_mask=false",
        "--run-dir",
        str(run),
    ]
    assert main(args) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert {"IoU", "mIoU", "Precision", "Recall", "IoU_car"} <= set(metrics) and "RayIoU" not in metrics
    assert metrics["eval_mask"] == "none" and metrics["train_masks"] == {"voxel_labels": "none"}
    assert "SemanticKITTI SSC (semantic-kitti-api scorer" in capsys.readouterr().out


def test_plugin_label_sources_and_transforms_run_in_the_reader(tree, toy_extensions):
    dm = module(tree, label_sources={"ids": {"type": "toy_ids", "offset": 3}}, transforms=[{"type": "toy_tag"}],
                registry=toy_extensions)
    batch = dm.collate([dm.dataset("train")[i] for i in range(2)])
    assert torch.equal(batch.extras["toy_ids"], torch.tensor([[3, -1], [3, 4]]))
    assert batch.extras["toy_num_classes"] == [20, 20]
    tags = batch.extras["toy_tag"]  # no rule declared: a list
    assert isinstance(tags, list) and torch.equal(torch.stack(tags), torch.tensor([[0.0, 0.0], [1.0, 0.0]]))
