"""Pseudo labels from files (documented layout, class-mapping table) and the synthetic world's realism knobs."""

import numpy as np
import pytest
import torch

from occplug.data import OCC3D_CLASSES, SEMANTIC_KITTI_CLASSES
from occplug.data.formats import FormatError
from occplug.data.pseudo_labels import PseudoLabelSource, load_mapping
from occplug.data.synthetic import SyntheticDataModule, SyntheticDataset, default_cache_dir, preset
from occplug.data.synthetic.pseudo import FOREIGN_CLASSES, SyntheticPseudoLabels, mapping_table, pseudo_realism

TINY = preset("tiny")
FOREIGN_CLASSES_ID = {name: i for i, name in FOREIGN_CLASSES.items()}


@pytest.fixture(scope="module")
def frame():
    return SyntheticDataset(TINY, "train", cache_dir=default_cache_dir())[0]


def sources(root):
    return {
        "depth": str(root / "depth"),
        "semantics": [
            {"dir": str(root / "semantics"), "mapping": str(root / "mapping.yaml")},
            {"dir": str(root / "semantics_aux"), "mapping": str(root / "mapping_aux.yaml")},
        ],
        "features": str(root / "features"),
    }


def test_written_pseudo_labels_read_back_through_the_mapping_table(frame, tmp_path):
    labeler = SyntheticPseudoLabels("default")
    labeler.write(frame, tmp_path)
    (tmp_path / "mapping.yaml").write_text(mapping_table("occ3d"))
    (tmp_path / "mapping_aux.yaml").write_text(mapping_table("occ3d", source="auxiliary"))
    assert (tmp_path / "depth" / frame.token / "CAM_FRONT.npy").is_file()
    assert (tmp_path / "semantics_aux" / frame.token / "CAM_BACK.png").is_file()
    assert (tmp_path / "semantics" / frame.token / "CAM_BACK.png").is_file()
    read = PseudoLabelSource(sources(tmp_path), OCC3D_CLASSES).attach(frame)
    made = labeler.attach(frame)
    assert torch.allclose(read.pseudo_depth, made.pseudo_depth)
    assert torch.equal(read.pseudo_semantics, made.pseudo_semantics)
    assert torch.allclose(read.pseudo_features, made.pseudo_features, atol=2e-3)  # stored as float16
    h, w = frame.image_size
    f = labeler.realism
    assert read.pseudo_features.shape == (6, f.feature_dim, h // f.feature_stride, w // f.feature_stride)


def test_maps_of_another_resolution_are_resized_to_the_image(frame, tmp_path):
    cams = frame.camera_names
    for c, cam in enumerate(cams):
        folder = tmp_path / "depth" / frame.token
        folder.mkdir(parents=True, exist_ok=True)
        d = frame.depth[c][::2, ::2].numpy()  # half resolution, as a uint16 PNG in KITTI's depth * 256
        from occplug.data.imageio import write_map

        write_map(folder / f"{cam}.png", np.round(d * 256).astype(np.int64))
    read = PseudoLabelSource({"depth": str(tmp_path / "depth")}, OCC3D_CLASSES).attach(frame)
    assert read.pseudo_depth.shape == frame.depth.shape
    assert torch.allclose(read.pseudo_depth[:, ::2, ::2], frame.depth[:, ::2, ::2], atol=1 / 256)


def test_realism_knobs(frame):
    perfect = SyntheticPseudoLabels("perfect").attach(frame)
    assert torch.allclose(perfect.pseudo_depth, frame.depth)
    noisy = SyntheticPseudoLabels("noisy").attach(frame)
    on = frame.depth > 0
    rel = (noisy.pseudo_depth[on] - frame.depth[on]).abs() / frame.depth[on]
    assert 0.02 < float(rel.median()) < 0.5
    truth = frame.semantics_2d
    # the foreign taxonomy merges classes no table can split again (as in OccLE's Table B.1) ...
    merged = (truth == 5) | (truth == 0) | (truth == 255)
    agree = lambda p: float((p.pseudo_semantics == truth)[~merged].float().mean())  # noqa: E731
    assert agree(perfect) == 1.0  # cones (8) included: the perfect auxiliary supplies them
    assert torch.equal(
        perfect.pseudo_semantics[truth == 5], torch.full_like(truth[truth == 5], 10)
    )  # construction -> truck
    # ... and noise / boundary errors cost accuracy
    assert 0.6 < agree(noisy) < agree(SyntheticPseudoLabels("default").attach(frame)) < 1.0
    # deterministic per (seed, token, camera)
    again = SyntheticPseudoLabels("noisy").attach(frame)
    assert torch.equal(again.pseudo_semantics, noisy.pseudo_semantics) and torch.equal(
        again.pseudo_depth, noisy.pseudo_depth
    )
    assert pseudo_realism({"preset": "noisy", "depth_noise": 0.0}).depth_noise == 0.0
    with pytest.raises(ValueError, match="unknown knob 'depth_nosie'"):
        pseudo_realism({"depth_nosie": 0.1})


def test_synthetic_data_module_makes_pseudo_labels_on_the_fly():
    dm = SyntheticDataModule(
        preset="tiny",
        train_scenes=1,
        pseudo_labels={"synthetic": "perfect", "kinds": ["depth"]},
        augment={"image": {"size": [24, 48]}},
    )
    f = dm.dataset("train")[0]
    assert f.pseudo_depth.shape == (6, 24, 48) and f.pseudo_semantics is None
    with pytest.raises(ValueError, match="only 'kinds'"):
        SyntheticDataModule(preset="tiny", pseudo_labels={"synthetic": "default", "depth": "x"})


def test_mapping_table_errors_name_the_file(tmp_path):
    path = tmp_path / "map.yaml"
    path.write_text(mapping_table("occ3d").replace("driveable_surface", "drivable_surface"))
    with pytest.raises(
        FormatError,
        match=r"map\.yaml: map\.road: unknown target class 'drivable_surface'; did you mean 'driveable_surface'",
    ):
        load_mapping(path, OCC3D_CLASSES)
    path.write_text("classes: {1: road}\nmap: {raod: driveable_surface}\n")
    with pytest.raises(FormatError, match="unknown foreign class 'raod'.*did you mean 'road'"):
        load_mapping(path, OCC3D_CLASSES)
    path.write_text("map: {}\n")
    with pytest.raises(FormatError, match="needs 'classes'"):
        load_mapping(path, OCC3D_CLASSES)
    path.write_text("classes: [\n")
    with pytest.raises(FormatError, match="invalid YAML"):
        load_mapping(path, OCC3D_CLASSES)
    lut = load_mapping(_write(tmp_path / "ok.yaml", mapping_table("occ3d")), OCC3D_CLASSES)
    assert lut[98] == OCC3D_CLASSES.index("driveable_surface") and lut[142] == 255 and lut[7] == 255
    assert set(FOREIGN_CLASSES) >= {98, 100, 174, 176}


def test_missing_files_fail_in_one_line_or_give_empty_maps(frame, tmp_path):
    (tmp_path / "depth").mkdir()
    with pytest.raises(FormatError, match=rf"depth/{frame.token}/CAM_FRONT\.png: no such file"):
        PseudoLabelSource({"depth": str(tmp_path / "depth")}, OCC3D_CLASSES).attach(frame)
    empty = PseudoLabelSource({"depth": str(tmp_path / "depth"), "missing": "empty"}, OCC3D_CLASSES).attach(frame)
    assert empty.pseudo_depth.shape == frame.depth.shape and not empty.pseudo_depth.any()
    with pytest.raises(FileNotFoundError, match="is not a folder"):
        PseudoLabelSource({"features": str(tmp_path / "nope")}, OCC3D_CLASSES)
    with pytest.raises(ValueError, match="did you mean 'semantics'"):
        PseudoLabelSource({"semantic": str(tmp_path)}, OCC3D_CLASSES)


def _write(path, text):
    path.write_text(text)
    return path


def test_feature_maps_read_from_npz_under_the_features_key(frame, tmp_path):
    labeler = SyntheticPseudoLabels("default")
    labeler.write(frame, tmp_path)
    npy = PseudoLabelSource({"features": str(tmp_path / "features")}, OCC3D_CLASSES).attach(frame).pseudo_features
    for path in sorted((tmp_path / "features" / frame.token).glob("*.npy")):
        np.savez_compressed(path.with_suffix(".npz"), features=np.load(path))
        path.unlink()
    read = PseudoLabelSource({"features": str(tmp_path / "features")}, OCC3D_CLASSES).attach(frame)
    assert torch.equal(read.pseudo_features, npy)  # the same arrays, from .npz
    victim = tmp_path / "features" / frame.token / f"{frame.camera_names[0]}.npz"
    np.savez_compressed(victim, feats=np.zeros((2, 3, 4), np.float16))
    with pytest.raises(FormatError, match=rf"{victim.name}: no 'features' array \(keys: feats\)"):
        PseudoLabelSource({"features": str(tmp_path / "features")}, OCC3D_CLASSES).attach(frame)


def test_several_semantic_sources_merge_by_precedence_through_their_tables(tmp_path):
    from occplug.data import Frame
    from occplug.data.pseudo_labels import merge_semantics

    targets = ["road", "car", "cone", "tree"]  # ids 0..3
    # the primary (dataset-specific) lacks cones; the auxiliary (open-vocabulary) has them, in its own ids
    (tmp_path / "primary.yaml").write_text(
        "classes: {0: unlabeled, 1: street, 2: automobile, 3: plant}\n"
        "map: {street: road, automobile: car, plant: tree, unlabeled: ignore}\n"
    )
    (tmp_path / "aux.yaml").write_text(
        "classes: {10: traffic cone, 11: vehicle, 12: background}\nmap: {traffic cone: cone, vehicle: car}\n"
    )
    primary = np.array([[1, 2, 0], [3, 0, 2]], dtype=np.int64)
    aux = np.array([[12, 11, 10], [10, 12, 12]], dtype=np.int64)
    for name, ids in (("primary", primary), ("aux", aux)):
        (tmp_path / name / "tok").mkdir(parents=True)
        np.save(tmp_path / name / "tok" / "CAM.npy", ids)
    frame = Frame(
        images=torch.zeros(1, 3, 2, 3),
        intrinsics=torch.eye(3)[None],
        cam_to_ego=torch.eye(4)[None],
        img_aug=torch.eye(3)[None],
        ego_to_global=torch.eye(4, dtype=torch.float64),
        timestamp=0.0,
        scene="s",
        frame_index=0,
        token="tok",
        camera_names=("CAM",),
    )
    both = [{"dir": "primary", "mapping": "primary.yaml"}, {"dir": "aux", "mapping": "aux.yaml"}]
    merged = PseudoLabelSource({"semantics": both}, targets, base=tmp_path).attach(frame).pseudo_semantics
    # cone only from the auxiliary (where the primary is silent); the primary's tree wins over the auxiliary's
    # cone at [1, 0]; nobody speaks at [1, 1]
    assert merged.tolist() == [[[0, 1, 2], [3, 255, 1]]]
    reverse = PseudoLabelSource({"semantics": both[::-1]}, targets, base=tmp_path).attach(frame).pseudo_semantics
    assert reverse.tolist() == [[[0, 1, 2], [2, 255, 1]]]
    single = PseudoLabelSource({"semantics": both[0]}, targets, base=tmp_path).attach(frame).pseudo_semantics
    assert single.tolist() == [[[0, 1, 255], [3, 255, 1]]]
    assert merge_semantics(
        [torch.tensor([255, 255, 4]), torch.tensor([1, 255, 2]), torch.tensor([3, 5, 3])]
    ).tolist() == [1, 5, 4]
    with pytest.raises(ValueError, match=r"pseudo_labels.semantics\[1\]: needs 'mapping'"):
        PseudoLabelSource({"semantics": [both[0], {"dir": "aux"}]}, targets, base=tmp_path)


def _train_frames():
    ds = SyntheticDataset(TINY, "train", cache_dir=default_cache_dir())
    return [ds[i] for i in range(len(ds))]


def test_two_semantic_sources_the_primary_lacks_cones_the_auxiliary_supplies_them():
    frames = _train_frames()
    cone, barrier = OCC3D_CLASSES.index("traffic_cone"), OCC3D_CLASSES.index("barrier")
    assert any((f.semantics_2d == cone).any() for f in frames)
    default = SyntheticPseudoLabels("default")
    primary_only = SyntheticPseudoLabels({"auxiliary": False})
    found = wrong = 0
    for f in frames:
        maps = default.maps(f)
        truth = f.semantics_2d
        # two taxonomies: the primary never says cone (no such foreign class), the auxiliary has it
        assert not (default._lut[maps["semantics"]] == cone).any()
        assert set(maps["semantics_aux"].unique().tolist()) <= set(range(7))
        merged = default.attach(f).pseudo_semantics
        alone = primary_only.attach(f).pseudo_semantics
        assert not (alone == cone).any()
        # the auxiliary only fills what the primary leaves unknown: wherever the primary speaks, it wins
        speaks = alone != 255
        assert torch.equal(merged[speaks], alone[speaks])
        found += int(((merged == cone) & (truth == cone)).sum())
        wrong += int(((maps["semantics_aux"] == 1) != (truth == cone)).sum())
    assert found >= 10  # tiny cones: the primary's boundary errors cover many of their pixels
    assert wrong > 0  # imperfect: the auxiliary's cone masks are not exactly the cones
    perfect = SyntheticPseudoLabels("perfect")
    f = next(f for f in frames if (f.semantics_2d == cone).any())
    assert torch.equal(
        perfect.attach(f).pseudo_semantics[f.semantics_2d == cone],
        torch.full_like(f.semantics_2d[f.semantics_2d == cone], cone),
    )
    assert barrier != cone
    table = mapping_table("occ3d", source="auxiliary")
    lut = load_mapping(_write_tmp(table), OCC3D_CLASSES)
    assert lut[1] == cone and (lut[[0, 2, 3, 4, 5, 6]] == 255).all()


def test_primary_lacks_a_class_the_auxiliary_supplies_it_and_the_written_tables_agree(tmp_path):
    frames = _train_frames()
    veg = OCC3D_CLASSES.index("vegetation")
    lacks = {"primary_lacks": ["vegetation"]}
    aligned = SyntheticPseudoLabels(lacks)
    primary_only = SyntheticPseudoLabels({**lacks, "auxiliary": False})
    default = SyntheticPseudoLabels("default")
    perfect, perfect_lacking = SyntheticPseudoLabels("perfect"), SyntheticPseudoLabels({**lacks, "preset": "perfect"})
    tree = 4  # the auxiliary's "tree" prompt
    truth_veg = filled = default_veg = 0
    for f in frames:
        maps = aligned.maps(f)
        # the primary has no vegetation class: its raw ids never name it, noise included
        assert not (aligned._lut[maps["semantics"]] == veg).any()
        alone = primary_only.attach(f).pseudo_semantics
        merged = aligned.attach(f).pseudo_semantics
        assert not (alone == veg).any()
        speaks = alone != 255
        assert torch.equal(merged[speaks], alone[speaks])  # the auxiliary only fills unknown pixels
        assert torch.equal(
            merged[~speaks & (maps["semantics_aux"] == tree)],
            torch.full_like(merged, veg)[~speaks & (maps["semantics_aux"] == tree)],
        )
        truth = f.semantics_2d == veg
        truth_veg += int(truth.sum())
        filled += int((merged[truth] == veg).sum())
        default_veg += int((default.attach(f).pseudo_semantics[truth] == veg).sum())
        # with perfect segmenters the perfect auxiliary supplies exactly what the primary lacks: nothing changes
        assert torch.equal(perfect_lacking.attach(f).pseudo_semantics, perfect.attach(f).pseudo_semantics)
    assert truth_veg > 1000
    # the auxiliary misses blobs (auxiliary_miss) and the primary's boundary errors bleed in: most, not all
    assert 0.6 < filled / truth_veg < default_veg / truth_veg + 0.05
    assert default_veg / truth_veg > 0.8
    # the tables say the same: the auxiliary's maps "tree" (and the cone), the primary's leaves vegetation out
    aux = load_mapping(
        _write_tmp(mapping_table("occ3d", source="auxiliary", primary_lacks=["vegetation"])), OCC3D_CLASSES
    )
    assert aux[tree] == veg and aux[1] == OCC3D_CLASSES.index("traffic_cone") and (aux[[0, 2, 3, 5, 6]] == 255).all()
    primary_table = mapping_table("occ3d", primary_lacks=["vegetation"])
    assert "vegetation" not in primary_table.split("map:")[0]
    assert load_mapping(_write_tmp(primary_table), OCC3D_CLASSES)[FOREIGN_CLASSES_ID["vegetation"]] == 255
    assert load_mapping(_write_tmp(mapping_table("occ3d")), OCC3D_CLASSES)[FOREIGN_CLASSES_ID["vegetation"]] == veg
    # written and read back through those tables, the merged labels are what attach() makes
    f = next(f for f in frames if (f.semantics_2d == veg).any())
    aligned.write(f, tmp_path)
    (tmp_path / "mapping.yaml").write_text(primary_table)
    (tmp_path / "mapping_aux.yaml").write_text(mapping_table("occ3d", source="auxiliary", primary_lacks=["vegetation"]))
    read = PseudoLabelSource(sources(tmp_path), OCC3D_CLASSES).attach(f)
    assert torch.equal(read.pseudo_semantics, aligned.attach(f).pseudo_semantics)
    # SemanticKITTI: "person" names its person class; it has no cone, so the cone prompt stays unmapped
    ssc = mapping_table("semantickitti", source="auxiliary", primary_lacks=["pedestrian"])
    assert "person: person" in ssc and "traffic cone: ignore" in ssc
    # the maps change only with the knob (the cache key too)
    assert SyntheticPseudoLabels(lacks).cache_key() != default.cache_key()


def test_primary_lacks_drops_merged_and_split_foreign_classes_in_every_path():
    frames = _train_frames()
    occ = {n: OCC3D_CLASSES.index(n) for n in ("manmade", "truck", "construction_vehicle", "pedestrian", "vegetation")}
    ids = FOREIGN_CLASSES_ID
    # manmade splits into building and wall; truck takes the construction vehicles merged into it
    noisy = SyntheticPseudoLabels({"preset": "noisy", "primary_lacks": ["truck", "manmade"]})
    plain = SyntheticPseudoLabels("noisy")
    seen_before = set()
    for f in frames:
        raw = noisy.maps(f)["semantics"]
        assert not torch.isin(raw, torch.tensor([ids["building"], ids["wall"], ids["truck"]])).any()
        assert (raw[f.semantics_2d == occ["construction_vehicle"]] == ids["unlabeled"]).all()
        seen_before |= set(plain.maps(f)["semantics"].unique().tolist())
    assert {ids["building"], ids["wall"], ids["truck"]} <= seen_before  # the frames do hold them without the knob
    table = load_mapping(
        _write_tmp(mapping_table("occ3d", source="auxiliary", primary_lacks=["manmade"])), OCC3D_CLASSES
    )
    assert table[5] == occ["manmade"]  # the "building" prompt
    # SemanticKITTI: the auxiliary's "person" fills the person class the primary lacks
    person = SEMANTIC_KITTI_CLASSES.index("person")
    kitti = SyntheticPseudoLabels({"primary_lacks": ["pedestrian"]}, taxonomy="semantickitti")
    kitti_alone = SyntheticPseudoLabels({"primary_lacks": ["pedestrian"], "auxiliary": False}, taxonomy="semantickitti")
    filled = 0
    for f in frames:
        assert not (kitti_alone.attach(f).pseudo_semantics == person).any()
        merged = kitti.attach(f).pseudo_semantics
        filled += int((merged[f.semantics_2d == occ["pedestrian"]] == person).sum())
    assert filled > 0
    # without the foreign taxonomy (target ids, no auxiliary) the lacked class is unknown, noise included
    identity = SyntheticPseudoLabels({"preset": "noisy", "foreign_taxonomy": False, "primary_lacks": ["vegetation"]})
    for f in frames:
        sem = identity.attach(f).pseudo_semantics
        assert not (sem == occ["vegetation"]).any()
        assert (sem[f.semantics_2d == occ["vegetation"]] == 255).float().mean() > 0.5  # boundary errors move some


def test_label_alignment_reproduces_a_hand_written_example_through_the_shipped_tables():
    from occplug.data.pseudo_labels import merge_semantics

    def align(primary, aux, lacks=()):
        lut = load_mapping(_write_tmp(mapping_table("occ3d", primary_lacks=lacks)), OCC3D_CLASSES)
        aux_lut = load_mapping(
            _write_tmp(mapping_table("occ3d", source="auxiliary", primary_lacks=lacks)), OCC3D_CLASSES
        )
        return merge_semantics([torch.as_tensor(lut)[primary].long(), torch.as_tensor(aux_lut)[aux].long()])

    # the primary's foreign ids (Table B.1's style): car, building, wall, unlabeled / road, sky, vegetation, bicyclist
    primary = torch.tensor([[176, 35, 191, 194], [98, 142, 174, 127]])
    # the auxiliary's prompts: background x 2, vehicle, traffic cone / person, tree, background x 2
    aux = torch.tensor([[0, 0, 2, 1], [3, 4, 0, 0]])
    car, manmade, cone, road, veg, bicycle = 4, 15, 8, 11, 16, 2
    # by hand: building and wall merge into manmade, the bicyclist is a bicycle, sky has no class; the auxiliary
    # fills only the cone (its only mapped prompt) where the primary is unknown; the primary wins where it speaks
    assert align(primary, aux).tolist() == [[car, manmade, manmade, cone], [road, 255, veg, bicycle]]
    # the primary lacks man-made structure and vegetation: its tables drop them, the auxiliary's building and tree
    # prompts fill them, and the tree mask spilling onto the sky labels it vegetation
    aux = torch.tensor([[0, 5, 5, 1], [3, 4, 4, 0]])
    lacks = ["manmade", "vegetation"]
    assert align(primary, aux, lacks).tolist() == [[car, manmade, manmade, cone], [road, veg, veg, bicycle]]
    assert align(primary, torch.zeros_like(aux), lacks).tolist() == [[car, 255, 255, 255], [road, 255, 255, bicycle]]


def test_primary_lacks_rejects_what_is_no_class_list():
    with pytest.raises(ValueError, match=r"primary_lacks: unknown class 'trees' \(valid: barrier, .*vegetation"):
        pseudo_realism({"primary_lacks": ["trees"]})
    with pytest.raises(ValueError, match="primary_lacks: unknown class 'traffic_cone'"):
        pseudo_realism({"primary_lacks": ["traffic_cone"]})  # lacked always; naming it is a mistake
    with pytest.raises(ValueError, match="primary_lacks must be a list of class names, got 'vegetation'"):
        pseudo_realism({"primary_lacks": "vegetation"})
    with pytest.raises(ValueError, match="primary_lacks must be a list of class names, got 'vegetation'"):
        mapping_table("occ3d", source="auxiliary", primary_lacks="vegetation")
    assert pseudo_realism({"primary_lacks": ["vegetation", "manmade", "manmade"]}).primary_lacks == (
        "manmade",
        "vegetation",
    )


def _write_tmp(text):
    import tempfile
    from pathlib import Path

    path = Path(tempfile.mkdtemp()) / "aux.yaml"
    path.write_text(text)
    return path


def test_features_cluster_by_class_but_are_no_one_to_one_code():
    frames = _train_frames()

    def nearest_centroid_accuracy(labeler):
        xs, ys = [], []
        s = labeler.realism.feature_stride
        for f in frames:
            x = labeler.attach(f).pseudo_features  # (N, F, h, w)
            _, c, h, w = x.shape
            y = f.semantics_2d[:, s // 2 :: s, s // 2 :: s][:, :h, :w]  # the class at each cell's centre
            xs.append(x.permute(0, 2, 3, 1).reshape(-1, c))
            ys.append(y.reshape(-1))
        x, y = torch.cat(xs), torch.cat(ys)
        x, y = x[y != 255], y[y != 255]
        classes = y.unique()
        centroids = torch.stack([x[y == k].mean(0) for k in classes])
        pred = classes[torch.cdist(x, centroids).argmin(1)]
        majority = max(float((y == k).float().mean()) for k in classes)
        return float((pred == y).float().mean()), majority, len(classes)

    acc, majority, k = nearest_centroid_accuracy(SyntheticPseudoLabels("default", kinds=("features",)))
    assert k >= 10 and acc > majority + 0.3  # far above chance (1 / k) and above always-the-biggest-class
    assert acc < 0.9  # but classes overlap: no one-to-one code of the true class
    noisy, _, _ = nearest_centroid_accuracy(SyntheticPseudoLabels("noisy", kinds=("features",)))
    assert noisy < acc


def test_synthetic_pseudo_maps_are_cached_on_disk_and_read_back_equal(frame, tmp_path, monkeypatch):
    fresh = SyntheticPseudoLabels("default").maps(frame)
    cached = SyntheticPseudoLabels("default", cache_dir=tmp_path)
    first = cached.maps(frame)
    assert len(list(tmp_path.rglob("*.pt"))) == 1
    monkeypatch.setattr(cached, "_make_maps", lambda f: pytest.fail("made again instead of read from the cache"))
    second = cached.maps(frame)
    for key in fresh:
        assert torch.equal(first[key], fresh[key]) and torch.equal(second[key], fresh[key])
    # other settings use another entry
    assert SyntheticPseudoLabels("noisy", cache_dir=tmp_path).cache_key() != cached.cache_key()
