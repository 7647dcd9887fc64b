"""``occplug data pseudo-labels nuscenes``: per-image maps named by sample_data token (or image file stem) in a
foreign layout -> occplug's <token>/<camera> layout; read back through the pseudo-label reader they equal the
source maps; bad inputs exit 2 with one line naming the file and leave nothing behind."""

import contextlib
import io
import json
import os
import shutil

import numpy as np
import pytest
import torch
import yaml
from kornia import io as kio

from occplug.cli import main
from occplug.data.imageio import png_bit_depth, read_map
from occplug.data.nuscenes.index import read_index
from occplug.data.nuscenes.reader import Occ3DNuScenesDataModule
from occplug.data.synthetic import preset

GRID = preset("tiny").grid.to_dict()
TABLES = "v1.0-trainval"


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    """A tiny nuScenes-shaped tree (3 train + 2 val samples, 6 cameras of 32 x 64) with synthetic pseudo labels
    in occplug's layout (``pseudo/``) and its prepared index (``index/``)."""
    root = tmp_path_factory.mktemp("pseudo_import") / "tree"
    with contextlib.redirect_stdout(io.StringIO()):
        args = ["--format", "occ3d", "--preset", "tiny", "--splits", "train", "val", "--pseudo", "default"]
        assert main(["data", "synth", *args, "--out", str(root), "train_scenes=1"]) == 0
        assert (
            main(
                ["data", "prepare", "nuscenes", "--root", str(root), "--version", TABLES, "--occ", str(root)]
                + ["--out", str(root / "index"), "--splits", str(root / "splits.json")]
            )
            == 0
        )
    return root


def camera_records(tree):
    """The camera sample_data records of the tree: ``(sample token, channel, sample_data token, image stem)``."""
    rows = json.loads((tree / TABLES / "sample_data.json").read_text())
    out = []
    for r in rows:
        channel = r["filename"].split("/")[1]
        if channel.startswith("CAM_"):
            out.append((r["sample_token"], channel, r["token"], os.path.basename(r["filename"]).rsplit(".", 1)[0]))
    return out


def write_uint16_png(path, values):
    path.parent.mkdir(parents=True, exist_ok=True)
    kio.write_image(str(path), torch.from_numpy(values.astype(np.int32)).to(torch.uint16)[None].contiguous())


def foreign(tree, dst, name_by="token", depth_as="npy", semantics_as="png"):
    """The tree's pseudo labels as a segmenter would write them: one file per image, named by its sample_data
    token (``name_by="token"``) or its image file's stem, in per-camera sub-folders; depth as float32 ``.npy`` or
    a 16-bit ``.png`` of metres * 500 (2 mm steps: the world reaches 71 m, past the 65.535 m of millimetres),
    semantics as the PNG or an int64 ``.npy``."""
    src = tree / "pseudo"
    for sample, cam, sd, stem in camera_records(tree):
        name = sd if name_by == "token" else stem
        depth = src / "depth" / sample / f"{cam}.npy"
        (dst / "depth" / cam).mkdir(parents=True, exist_ok=True)
        if depth_as == "npy":
            shutil.copyfile(depth, dst / "depth" / cam / f"{name}.npy")
        else:
            write_uint16_png(dst / "depth" / cam / f"{name}.png", np.round(np.load(depth) * 500))
        sem = src / "semantics" / sample / f"{cam}.png"
        (dst / "semantics" / cam).mkdir(parents=True, exist_ok=True)
        if semantics_as == "png":
            shutil.copyfile(sem, dst / "semantics" / cam / f"{name}.png")
        else:
            np.save(dst / "semantics" / cam / f"{name}.npy", read_map(sem).astype(np.int64))
    return dst


@pytest.fixture(scope="module")
def maps(tree, tmp_path_factory):
    return foreign(tree, tmp_path_factory.mktemp("foreign") / "maps")


def convert(tree, maps, out, *extra, kinds=("depth", "semantics"), capsys=None):
    args = ["data", "pseudo-labels", "nuscenes", "--index", str(tree / "index"), "--out", str(out), "--no-progress"]
    args += [a for k in kinds for a in (f"--{k}", str(maps / k))]
    return main([*args, *extra])


def module(tree, pseudo_labels, **kw):
    return Occ3DNuScenesDataModule(
        root=str(tree), index=str(tree / "index"), grid=GRID, pseudo_labels=pseudo_labels, **kw
    )


def test_round_trip_by_sample_data_token_equals_the_source_maps_on_every_frame_and_window(tree, maps, tmp_path, capsys):
    src = tmp_path / "maps"
    shutil.copytree(maps, src)
    # one map as a tool might write it: float64, with a leading singleton axis (converted to float32 (H, W))
    sample, cam, sd, _ = camera_records(tree)[0]
    np.save(src / "depth" / cam / f"{sd}.npy", np.load(src / "depth" / cam / f"{sd}.npy").astype(np.float64)[None])
    mapping = tree / "pseudo" / "semantics_mapping.yaml"
    out = tmp_path / "out"
    assert convert(tree, src, out, "--mapping", str(mapping)) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0] == f"wrote the pseudo labels of 5 samples x 6 cameras (train 3, val 2) to {out}"
    assert lines[1].startswith(f"  depth: 30 maps (30 .npy; 1 converted) from {src / 'depth'}; 0 maps there not needed")
    assert lines[2].startswith(f"  semantics: 30 maps (30 .png; 0 converted) from {src / 'semantics'}; 0 maps")
    # the layout: <out>/<kind>/<sample token>/<CAMERA>.<ext>, the table beside
    assert sorted(p.name for p in out.iterdir()) == ["depth", "semantics", "semantics_mapping.yaml"]
    assert (out / "semantics_mapping.yaml").read_text() == mapping.read_text()
    assert np.load(out / "depth" / sample / f"{cam}.npy").dtype == np.float32
    # the printed data node reads the output; every frame and its window frames equal the tree's own maps
    node = yaml.safe_load(lines[3].removeprefix('read them with: "data.pseudo_labels=').removesuffix('"'))
    reference = {"depth": str(tree / "pseudo" / "depth"), "semantics": {"dir": str(tree / "pseudo" / "semantics")}}
    reference["semantics"]["mapping"] = str(mapping)
    converted = module(tree, node, adjacent_offsets=[-1, 1])
    original = module(tree, reference, adjacent_offsets=[-1, 1])
    for split, n in (("train", 3), ("val", 2)):
        a, b = converted.dataset(split), original.dataset(split)
        assert len(a) == n
        for i in range(n):
            fa, fb = a[i], b[i]
            for x, y in [(fa, fb), *((fa.adjacent[k], fb.adjacent[k]) for k in (-1, 1))]:
                assert x.token == y.token and x.pseudo_depth.shape == (6, 32, 64)
                assert torch.equal(x.pseudo_depth, y.pseudo_depth)
                assert torch.equal(x.pseudo_semantics, y.pseudo_semantics)
            assert (fa.pseudo_depth > 0).any() and (fa.pseudo_semantics != 255).any()  # not vacuous


def test_by_image_stem_png_depth_npy_semantics_one_split_hard_linked(tree, tmp_path, capsys):
    src = foreign(tree, tmp_path / "maps", name_by="stem", depth_as="png", semantics_as="npy")
    out = tmp_path / "out"
    out.mkdir()  # an empty output folder is taken
    extra = ("--name-by", "stem", "--depth-scale", "500", "--splits", "val", "--link")
    assert convert(tree, src, out, *extra) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0] == f"wrote the pseudo labels of 2 samples x 6 cameras (val 2) to {out}"
    assert "depth: 12 maps (12 .png; 0 converted)" in lines[1] and "18 maps there not needed" in lines[1]
    assert "semantics: 12 maps (12 .png; 12 converted)" in lines[2] and "18 maps there not needed" in lines[2]
    assert "mapping: MAPPING.yaml" in lines[3] and "scale: 500.0" in lines[3]
    val = {s["token"] for s in read_index(tree / "index").samples if s["split"] == "val"}
    assert {p.name for p in (out / "depth").iterdir()} == {p.name for p in (out / "semantics").iterdir()} == val
    for sample, cam, _, stem in camera_records(tree):
        if sample not in val:
            continue
        depth_in, depth_out = src / "depth" / cam / f"{stem}.png", out / "depth" / sample / f"{cam}.png"
        assert os.stat(depth_in).st_ino == os.stat(depth_out).st_ino  # linked, not copied
        assert png_bit_depth(depth_out) == 16
        sem_out = out / "semantics" / sample / f"{cam}.png"
        assert np.array_equal(read_map(sem_out), np.load(src / "semantics" / cam / f"{stem}.npy"))
    # read back with the printed scale: the PNG values / 500, and the tree's semantics through its table
    pseudo = {
        "depth": {"dir": str(out / "depth"), "scale": 500.0},
        "semantics": {"dir": str(out / "semantics"), "mapping": str(tree / "pseudo" / "semantics_mapping.yaml")},
    }
    reference = {"semantics": {"dir": str(tree / "pseudo" / "semantics")}}
    reference["semantics"]["mapping"] = pseudo["semantics"]["mapping"]
    for got, ref in zip(module(tree, pseudo).dataset("val"), module(tree, reference).dataset("val"), strict=True):
        for c, cam in enumerate(got.camera_names):
            units = np.load(tree / "pseudo" / "depth" / got.token / f"{cam}.npy") * 500
            assert torch.equal(got.pseudo_depth[c], torch.from_numpy(np.round(units).astype(np.float32) / 500))
        assert torch.equal(got.pseudo_semantics, ref.pseudo_semantics)


def _first(tree, maps, kind, ext=None):
    """The first camera record's input map of ``kind`` (token naming)."""
    _, cam, sd, _ = camera_records(tree)[0]
    return maps / kind / cam / f"{sd}.{ext or ('npy' if kind == 'depth' else 'png')}"


def _damage(tree, maps, damage):
    """Apply ``damage`` to the foreign maps; returns (the path the error must name, what it must say)."""
    depth, sem = _first(tree, maps, "depth"), _first(tree, maps, "semantics")
    _, cam, sd, _ = camera_records(tree)[0]
    shape = np.load(depth).shape
    if damage == "missing":
        depth.unlink()
        return maps / "depth", f"no depth map for image samples/{cam}/"
    if damage == "unknown_token":
        np.save(maps / "depth" / "0123456789abcdef.npy", np.ones(shape, np.float32))
        return maps / "depth" / "0123456789abcdef.npy", "'0123456789abcdef' is no sample_data token of"
    if damage == "duplicate":
        (maps / "depth" / "elsewhere").mkdir()
        shutil.copyfile(depth, maps / "depth" / "elsewhere" / depth.name)
        return maps / "depth" / "elsewhere" / depth.name, f"a second depth map named '{sd}'"
    if damage == "int_depth":
        np.save(depth, np.ones(shape, np.int32))
        return depth, "depth map of dtype int32; expected float16/32/64 metres"
    if damage == "nan_depth":
        bad = np.load(depth)
        bad[0, 0] = np.nan
        np.save(depth, bad)
        return depth, "1 depth values are negative, NaN or infinite; expected metres >= 0"
    if damage == "shape":
        np.save(depth, np.ones((2, *shape), np.float32))
        return depth, f"depth map of shape (2, {shape[0]}, {shape[1]}); expected (H', W')"
    if damage == "transposed":
        np.save(depth, np.ones(shape[::-1], np.float32))
        return depth, "expected the image's aspect ratio (within 1%"
    if damage == "8bit_depth":
        depth.unlink()
        png = depth.with_suffix(".png")
        kio.write_image(str(png), torch.full((1, *shape), 7, dtype=torch.uint8))
        return png, "PNG of 8-bit samples; expected a 16-bit depth PNG"
    if damage == "unreadable":
        sem.write_bytes(b"not a png at all")
        return sem, "cannot read"
    if damage == "float_semantics":
        sem.unlink()
        np.save(sem.with_suffix(".npy"), np.zeros(shape, np.float32))
        return sem.with_suffix(".npy"), "semantic map of dtype float32; expected integer class ids"
    if damage == "id_outside_table":
        ids = read_map(sem)
        ids[0, 0] = 77
        write_uint16_png(sem, ids)
        return sem, "class ids 77 are not in the 'classes' of"
    raise AssertionError(damage)


DAMAGES = [
    "missing",
    "unknown_token",
    "duplicate",
    "int_depth",
    "nan_depth",
    "shape",
    "transposed",
    "8bit_depth",
    "unreadable",
    "float_semantics",
    "id_outside_table",
]


@pytest.mark.parametrize("damage", DAMAGES)
def test_bad_inputs_exit_2_in_one_line_naming_the_file_and_write_nothing(tree, maps, tmp_path, damage, capsys):
    src = tmp_path / "maps"
    shutil.copytree(maps, src)
    named, says = _damage(tree, src, damage)
    parent = tmp_path / "outputs"
    parent.mkdir()
    out = parent / "out"
    if damage in ("transposed", "unreadable"):
        out.mkdir()  # an existing empty output folder stays as it was
    capsys.readouterr()
    mapping = ("--mapping", str(tree / "pseudo" / "semantics_mapping.yaml"))
    assert convert(tree, src, out, *mapping) == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {named}: "), err
    assert says in err[0], err[0]
    assert captured.out == ""
    assert [p.name for p in parent.iterdir()] == (["out"] if out.exists() else [])  # no temporary folder left
    assert not out.exists() or not any(out.iterdir())


def test_usage_errors(tree, maps, tmp_path, capsys):
    def one_line(*args, kinds=("depth",)):
        capsys.readouterr()
        assert convert(tree, maps, tmp_path / "out", *args, kinds=kinds) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1, err
        return err[0]

    assert one_line(kinds=()) == "error: give --depth and/or --semantics, the folders of per-image maps"
    assert one_line("--mapping", "x.yaml") == "error: --mapping: a class-mapping table goes with --semantics"
    assert one_line("--depth-scale", "0") == "error: --depth-scale: expected a positive number, got 0.0"
    assert one_line("--splits", "tset").endswith("no sample of split 'tset' (splits: train, val)")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep").write_text("x")
    assert one_line() == f"error: --out {tmp_path / 'out'}: the folder exists and is not empty"
    assert (tmp_path / "out" / "keep").read_text() == "x"
