"""The class mapping tables in ``occplug.data.classes``: known entries, round trips, and one copy in the tree."""

from __future__ import annotations

from pathlib import Path

import occplug
from occplug.data.classes import (
    NUSCENES_LIDARSEG_CATEGORIES,
    NUSCENES_TO_OCC3D,
    OCC3D_CLASSES,
    OCC3D_TO_NUSCENES,
    SEMANTIC_KITTI_CLASSES,
    SEMANTIC_KITTI_LEARNING_MAP,
    SEMANTIC_KITTI_LEARNING_MAP_INV,
    nuscenes_to_occ3d,
)


def test_nuscenes_categories_map_to_the_occ3d_ids_of_their_names():
    assert OCC3D_CLASSES[nuscenes_to_occ3d("vehicle.car")] == "car"
    assert OCC3D_CLASSES[nuscenes_to_occ3d("human.pedestrian.child")] == "pedestrian"
    assert OCC3D_CLASSES[nuscenes_to_occ3d("movable_object.trafficcone")] == "traffic_cone"
    assert OCC3D_CLASSES[nuscenes_to_occ3d("flat.driveable_surface")] == "driveable_surface"
    assert nuscenes_to_occ3d("vehicle.ego") == 255 and nuscenes_to_occ3d("noise") == 255
    assert nuscenes_to_occ3d("animal") == 0 and nuscenes_to_occ3d("not.a.category") == 0  # unlisted: others


def test_occ3d_to_nuscenes_round_trips_every_class_but_free():
    assert sorted(OCC3D_TO_NUSCENES) == list(range(17))
    assert all(nuscenes_to_occ3d(OCC3D_TO_NUSCENES[i]) == i for i in range(17))
    assert set(OCC3D_TO_NUSCENES.values()) <= set(NUSCENES_LIDARSEG_CATEGORIES)


def test_lidarseg_ids_are_the_devkit_ones():
    assert len(NUSCENES_LIDARSEG_CATEGORIES) == 32
    assert NUSCENES_LIDARSEG_CATEGORIES.index("vehicle.car") == 17
    assert NUSCENES_LIDARSEG_CATEGORIES.index("flat.driveable_surface") == 24
    assert NUSCENES_LIDARSEG_CATEGORIES[31] == "vehicle.ego"
    assert set(NUSCENES_TO_OCC3D) <= set(NUSCENES_LIDARSEG_CATEGORIES)


def test_semantickitti_learning_map_known_entries_and_inverse():
    assert SEMANTIC_KITTI_CLASSES[SEMANTIC_KITTI_LEARNING_MAP[10]] == "car"
    assert SEMANTIC_KITTI_CLASSES[SEMANTIC_KITTI_LEARNING_MAP[252]] == "car"  # moving-car
    assert SEMANTIC_KITTI_CLASSES[SEMANTIC_KITTI_LEARNING_MAP[40]] == "road"
    assert SEMANTIC_KITTI_CLASSES[SEMANTIC_KITTI_LEARNING_MAP[70]] == "vegetation"
    assert sorted(SEMANTIC_KITTI_LEARNING_MAP_INV) == list(range(len(SEMANTIC_KITTI_CLASSES)))
    assert all(SEMANTIC_KITTI_LEARNING_MAP[SEMANTIC_KITTI_LEARNING_MAP_INV[c]] == c for c in range(20))


def test_each_table_has_one_copy_in_the_core():
    """A literal that only a copy of a table would hold appears in ``classes.py`` and nowhere else."""
    root = Path(occplug.__file__).parent
    markers = ('"vehicle.bus.bendy"', '"human.pedestrian.wheelchair"', "252: 1, 253: 7", "13: 50, 14: 51",
               "16: 15, 17: 0}")
    for marker in markers:
        holders = sorted(p.relative_to(root).as_posix() for p in root.rglob("*.py") if marker in p.read_text())
        assert holders == ["data/classes.py"], (marker, holders)


def test_occ3d_to_semantickitti_by_name():
    from occplug.data.classes import OCC3D_TO_SEMANTIC_KITTI as to_ssc

    assert len(to_ssc) == 256 and to_ssc[255] == 255
    same = ("car", "bicycle", "motorcycle", "truck", "sidewalk", "terrain", "vegetation")
    for name in same:
        assert SEMANTIC_KITTI_CLASSES[to_ssc[OCC3D_CLASSES.index(name)]] == name
    assert SEMANTIC_KITTI_CLASSES[to_ssc[OCC3D_CLASSES.index("pedestrian")]] == "person"
    assert SEMANTIC_KITTI_CLASSES[to_ssc[OCC3D_CLASSES.index("driveable_surface")]] == "road"
    assert SEMANTIC_KITTI_CLASSES[to_ssc[OCC3D_CLASSES.index("free")]] == "empty"
    assert to_ssc[OCC3D_CLASSES.index("traffic_cone")] == 255 and to_ssc[OCC3D_CLASSES.index("others")] == 255
