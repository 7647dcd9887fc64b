"""OccLE's Table B.1 as shipped mapping tables (configs/pseudo_labels/), read through occplug.data.pseudo_labels."""

from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from occplug.data import SEMANTIC_KITTI_CLASSES, Frame, PseudoLabelSource, load_mapping
from occplug.plugins import config_dirs

IGNORE = 255  # occplug.data.pseudo_labels: a pixel without a target class
TABLES = Path(config_dirs()["occle"]) / "pseudo_labels"
PRIMARY = TABLES / "primary_to_semantickitti.yaml"
AUXILIARY = TABLES / "auxiliary_to_semantickitti.yaml"

#: Table B.1 as printed (appendix B, arXiv 2505.20617v3), row by row: (SemanticKITTI id, class, image-segmentation
#: id, image class); SAM2's row has no id. Free (0) has no image class.
TABLE_B1 = [
    (1, "car", 176, "car"),
    (2, "bicycle", 175, "bicycle"),
    (3, "motorcycle", 178, "motorcycle"),
    (4, "truck", 182, "truck"),
    (5, "other-vehicle", 177, "autorickshaw"),
    (5, "other-vehicle", 180, "bus"),
    (5, "other-vehicle", 181, "train"),
    (5, "other-vehicle", 183, "trailer"),
    (5, "other-vehicle", 185, "slow_wheeled_object"),
    (6, "person", 125, "person"),
    (7, "bicyclist", 126, "rider_other"),
    (7, "bicyclist", 127, "bicyclist"),
    (8, "motorcyclist", 128, "motorcyclist"),
    (9, "road", 98, "road"),
    (10, "parking", 138, "parking_meter"),
    (11, "sidewalk", 100, "sidewalk_pavement"),
    (12, "other-ground", 31, "road_barrier"),
    (12, "other-ground", 32, "mailbox"),
    (12, "other-ground", 137, "fire_hydrant"),
    (12, "other-ground", 191, "wall"),
    (13, "building", 35, "building"),
    (14, "fence", 144, "fence"),
    (15, "vegetation", 131, "road_barrier"),
    (15, "vegetation", 174, "vegetation"),
    (16, "trunk", None, "trunk"),
    (17, "terrain", 102, "terrain"),
    (18, "pole", 143, "pole"),
    (18, "pole", 130, "streetlight"),
    (18, "pole", 145, "railing_banister"),
    (18, "pole", 146, "guard_rail"),
    (18, "pole", 162, "column"),
    (19, "traffic-sign", 135, "traffic_sign"),
    (19, "traffic-sign", 136, "traffic_light"),
]
#: Printed ids that are not MSeg's id of the printed name (MSeg's 31 and 32 are tunnel and bridge); the YAML header
#: documents both departures.
PRINTED_ID_TYPOS = {31: 131, 32: 132}
#: road_barrier is printed under two classes; one foreign class has one target, and the table keeps other-ground.
NOT_TAKEN = {("vegetation", "road_barrier"): "other-ground"}


def _table(path):
    return yaml.safe_load(path.read_text())


def test_every_target_is_a_semantickitti_class_and_both_tables_load():
    for path in (PRIMARY, AUXILIARY):
        targets = set(_table(path)["map"].values()) - {"ignore"}
        assert targets and targets <= set(SEMANTIC_KITTI_CLASSES), (path.name, targets - set(SEMANTIC_KITTI_CLASSES))
        lut = load_mapping(path, SEMANTIC_KITTI_CLASSES)  # raises on an unknown foreign or target class
        assert (lut != IGNORE).sum() == len([t for t in _table(path)["map"].values() if t != "ignore"])


def test_every_table_b1_row_appears_and_nothing_else():
    primary, auxiliary = _table(PRIMARY), _table(AUXILIARY)
    mseg_names = set()
    for kitti_id, kitti, printed_id, name in TABLE_B1:
        assert SEMANTIC_KITTI_CLASSES[kitti_id] == kitti  # the transcription's two columns agree
        if printed_id is None:  # SAM2's prompt
            assert auxiliary["map"][name] == kitti
            continue
        mseg_id = PRINTED_ID_TYPOS.get(printed_id, printed_id)
        assert primary["classes"][mseg_id] == name, (printed_id, name)
        assert primary["map"][name] == NOT_TAKEN.get((kitti, name), kitti), name
        mseg_names.add(name)
    assert set(primary["map"]) == mseg_names  # no class beyond the table's
    assert {k for k, v in auxiliary["map"].items() if v != "ignore"} == {"trunk"}
    # the MSeg universal taxonomy is complete: ids 0-193 and 255 (unlabeled), names unique
    assert sorted(primary["classes"]) == [*range(194), 255] and primary["classes"][255] == "unlabeled"
    assert len(set(primary["classes"].values())) == 195
    assert (primary["classes"][31], primary["classes"][32]) == ("tunnel", "bridge")  # why the printed ids are not used


def _frame(h, w):
    return Frame(
        images=torch.zeros(1, 3, h, w),
        intrinsics=torch.eye(3)[None],
        cam_to_ego=torch.eye(4)[None],
        img_aug=torch.eye(3)[None],
        ego_to_global=torch.eye(4, dtype=torch.float64),
        timestamp=0.0,
        scene="08",
        frame_index=0,
        token="08_000000",
        camera_names=("image_2",),
    )


@pytest.fixture
def maps(tmp_path):
    # MSeg (universal ids): car, vegetation, sky, bicyclist, road_barrier / road, parking_meter, wall, unlabeled,
    # tunnel (the id Table B.1 prints for road_barrier)
    mseg = np.array([[176, 174, 142, 127, 131], [98, 138, 191, 255, 31]], dtype=np.int64)
    # SAM2 (0 no mask, 1 trunk): a trunk mask over MSeg's vegetation and spilling onto the sky
    sam2 = np.array([[0, 1, 1, 0, 0], [0, 0, 0, 0, 0]], dtype=np.int64)
    for name, ids in (("mseg", mseg), ("sam2", sam2)):
        (tmp_path / name / "08_000000").mkdir(parents=True)
        np.save(tmp_path / name / "08_000000" / "image_2.npy", ids)
    return {
        "primary": {"dir": str(tmp_path / "mseg"), "mapping": str(PRIMARY)},
        "auxiliary": {"dir": str(tmp_path / "sam2"), "mapping": str(AUXILIARY)},
    }


def test_merged_labels_of_a_hand_made_example(maps):
    k = {name: i for i, name in enumerate(SEMANTIC_KITTI_CLASSES)}
    car, veg, trunk, cyclist, ground = k["car"], k["vegetation"], k["trunk"], k["bicyclist"], k["other-ground"]
    road, parking, none = k["road"], k["parking"], IGNORE

    def merged(*order):
        source = PseudoLabelSource({"semantics": [maps[o] for o in order]}, SEMANTIC_KITTI_CLASSES)
        return source.attach(_frame(2, 5)).pseudo_semantics.tolist()

    # by hand, primary first: MSeg decides where it has a class (its vegetation keeps the trunk pixel); SAM2's trunk
    # fills the sky pixel MSeg maps to nothing; road_barrier and wall are other-ground, parking_meter parking, the
    # printed id 31 (MSeg's tunnel) and unlabeled nothing
    assert merged("primary", "auxiliary") == [[[car, veg, trunk, cyclist, ground], [road, parking, ground, none, none]]]
    # SAM2 first (the paper's order, configs/semantickitti.yaml): its trunk mask wins over MSeg's vegetation too;
    # it maps nothing else, so every other pixel is MSeg's
    assert merged("auxiliary", "primary") == [
        [[car, trunk, trunk, cyclist, ground], [road, parking, ground, none, none]]
    ]
    assert merged("auxiliary") == [[[none, trunk, trunk, none, none], [none] * 5]]
