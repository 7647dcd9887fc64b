"""QueryOcc's Grounded-SAM -> Occ3D table (configs/pseudo_labels/grounded_sam_occ3d.yaml), read through
occplug.data.pseudo_labels."""

from pathlib import Path

import numpy as np
import yaml

from occplug.data import OCC3D_CLASSES, OCC3D_FREE, load_mapping
from occplug.plugins import config_dirs

IGNORE = 255  # occplug.data.pseudo_labels: a pixel without a target class
TABLE = Path(config_dirs()["queryocc"]) / "pseudo_labels" / "grounded_sam_occ3d.yaml"

#: The prompt -> id rule of OccNeRF's Grounded-SAM label generator (groundedsam_generate_sem_nusc.py, ``dic``),
#: transcribed, with the Occ3D class each id stands for.
PROMPTS = {
    "sedan": (1, "car"),
    "highway": (2, "driveable_surface"),
    "bus": (3, "bus"),
    "truck": (4, "truck"),
    "terrain": (5, "terrain"),
    "tree": (6, "vegetation"),
    "sidewalk": (7, "sidewalk"),
    "bicycle": (8, "bicycle"),
    "bicyclist": (8, "bicycle"),
    "barrier": (9, "barrier"),
    "barricade": (9, "barrier"),
    "person": (10, "pedestrian"),
    "pedestrian": (10, "pedestrian"),
    "building": (11, "manmade"),
    "bridge": (11, "manmade"),
    "pole": (11, "manmade"),
    "billboard": (11, "manmade"),
    "light": (11, "manmade"),
    "ashbin": (11, "manmade"),
    "motorcycle": (12, "motorcycle"),
    "motorcyclist": (12, "motorcycle"),
    "crane": (13, "construction_vehicle"),
    "trailer": (14, "trailer"),
    "cone": (15, "traffic_cone"),
    "sky": (16, "free"),
}


def _table():
    return yaml.safe_load(TABLE.read_text())


def test_the_table_loads_every_target_is_an_occ3d_class_and_every_prompt_maps_as_its_id():
    table = _table()
    targets = set(table["map"].values()) - {"ignore"}
    assert targets <= set(OCC3D_CLASSES), targets - set(OCC3D_CLASSES)
    lut = load_mapping(TABLE, OCC3D_CLASSES)  # raises on an unknown foreign or target class
    for prompt, (fid, target) in PROMPTS.items():
        assert OCC3D_CLASSES[lut[fid]] == target, prompt
    # every id the generator writes is listed (0: no mask, 255: its -1 in 8 bits), and nothing more
    assert sorted(table["classes"]) == [*range(17), 255]
    assert lut[0] == lut[255] == IGNORE
    assert (lut != IGNORE).sum() == 16  # ids 1..16
    # sky is free (QueryOcc's sky rays); no prompt gives others / other_flat
    assert lut[16] == OCC3D_FREE
    assert {"others", "other_flat"}.isdisjoint(OCC3D_CLASSES[t] for t in lut[lut != IGNORE])
    # the header's prompt list is the one transcribed above
    for prompt in PROMPTS:
        assert prompt in TABLE.read_text().split("classes:")[0], prompt


def test_a_hand_made_map_maps_to_occ3d_ids_as_the_reader_applies_the_table():
    k = {name: i for i, name in enumerate(OCC3D_CLASSES)}
    ids = np.array([[16, 16, 255, 0], [1, 2, 7, 11], [15, 10, 13, 6], [3, 4, 5, 8], [9, 12, 14, 16]], dtype=np.int64)
    lut = load_mapping(TABLE, OCC3D_CLASSES)
    got = lut[ids].tolist()  # PseudoLabelSource maps a map's foreign ids exactly so (then resizes)
    free = k["free"]
    assert got == [
        [free, free, IGNORE, IGNORE],
        [k["car"], k["driveable_surface"], k["sidewalk"], k["manmade"]],
        [k["traffic_cone"], k["pedestrian"], k["construction_vehicle"], k["vegetation"]],
        [k["bus"], k["truck"], k["terrain"], k["bicycle"]],
        [k["barrier"], k["motorcycle"], k["trailer"], free],
    ]
