"""Class taxonomies: Occ3D-nuScenes (the default) and SemanticKITTI SSC."""

from __future__ import annotations

__all__ = [
    "CLASS_GROUPS",
    "OCC3D_CLASSES",
    "OCC3D_COLORS",
    "OCC3D_DYNAMIC",
    "OCC3D_FREE",
    "OCC3D_NUM_CLASSES",
    "OCC3D_STATIC",
    "SEMANTIC_KITTI_CLASSES",
    "SEMANTIC_KITTI_COLORS",
    "SEMANTIC_KITTI_DYNAMIC",
    "SEMANTIC_KITTI_STATIC",
    "class_colors",
    "class_groups",
]

#: Occ3D-nuScenes class names indexed by id; id 17 is ``free`` (empty space).
OCC3D_CLASSES: tuple[str, ...] = (
    "others",
    "barrier",
    "bicycle",
    "bus",
    "car",
    "construction_vehicle",
    "motorcycle",
    "pedestrian",
    "traffic_cone",
    "trailer",
    "truck",
    "driveable_surface",
    "other_flat",
    "sidewalk",
    "terrain",
    "manmade",
    "vegetation",
    "free",
)
OCC3D_FREE: int = 17
#: Number of ids including ``free`` (the logits dimension of an Occ3D-style head).
OCC3D_NUM_CLASSES: int = 18

#: SemanticKITTI SSC class names indexed by id; 0 is empty, 255 is ignored (not listed).
SEMANTIC_KITTI_CLASSES: tuple[str, ...] = (
    "empty",
    "car",
    "bicycle",
    "motorcycle",
    "truck",
    "other-vehicle",
    "person",
    "bicyclist",
    "motorcyclist",
    "road",
    "parking",
    "sidewalk",
    "other-ground",
    "building",
    "fence",
    "vegetation",
    "trunk",
    "terrain",
    "pole",
    "traffic-sign",
)


# ---------------------------------------------------------------- dynamic / static groups
# The one definition of each taxonomy's dynamic (object) and static (surface / structure) classes;
# metrics report ``mIoU_dynamic`` / ``mIoU_static`` over them.

#: Occ3D-nuScenes object classes (the ten nuScenes detection classes, barrier and traffic cone
#: included: they are objects, not scene structure, even when they do not move).
OCC3D_DYNAMIC: tuple[str, ...] = (
    "barrier", "bicycle", "bus", "car", "construction_vehicle", "motorcycle", "pedestrian", "traffic_cone", "trailer",
    "truck",
)  # fmt: skip
#: Occ3D-nuScenes surface and structure classes. ``others`` and ``free`` are in neither group.
OCC3D_STATIC: tuple[str, ...] = ("driveable_surface", "other_flat", "sidewalk", "terrain", "manmade", "vegetation")

#: SemanticKITTI movable classes: vehicles and road users (the classes that SemanticKITTI's
#: moving-object labels can mark as moving).
SEMANTIC_KITTI_DYNAMIC: tuple[str, ...] = (
    "car", "bicycle", "motorcycle", "truck", "other-vehicle", "person", "bicyclist", "motorcyclist",
)  # fmt: skip
#: SemanticKITTI ground, structure and nature classes (poles, signs, fences and trunks are fixed
#: structure here, unlike Occ3D's barrier / cone objects). ``empty`` is in neither group.
SEMANTIC_KITTI_STATIC: tuple[str, ...] = (
    "road", "parking", "sidewalk", "other-ground", "building", "fence", "vegetation", "trunk", "terrain", "pole",
    "traffic-sign",
)  # fmt: skip

#: Taxonomy (its class-name tuple) -> ``{"dynamic": names, "static": names}``.
CLASS_GROUPS: dict[tuple[str, ...], dict[str, tuple[str, ...]]] = {
    OCC3D_CLASSES: {"dynamic": OCC3D_DYNAMIC, "static": OCC3D_STATIC},
    SEMANTIC_KITTI_CLASSES: {"dynamic": SEMANTIC_KITTI_DYNAMIC, "static": SEMANTIC_KITTI_STATIC},
}


def class_groups(class_names: tuple[str, ...] | list[str]) -> dict[str, tuple[int, ...]] | None:
    """``{"dynamic": ids, "static": ids}`` of a known taxonomy (Occ3D-nuScenes, SemanticKITTI), else None.

    Ids index ``class_names``; a name list that is not exactly one of the two taxonomies has no groups.
    """
    groups = CLASS_GROUPS.get(tuple(class_names))
    if groups is None:
        return None
    index = {n: i for i, n in enumerate(class_names)}
    return {k: tuple(index[n] for n in names) for k, names in groups.items()}


# ---------------------------------------------------------------- colours
# One ``(r, g, b)`` uint8 triple per class id, so ``numpy.asarray(COLORS, numpy.uint8)`` is the
# ``(K, 3)`` lookup table of a taxonomy. Every picture occplug draws takes its colours from here.

#: Occ3D-nuScenes colours indexed by id, the palette of the Occ3D / CVPR 2023 occupancy-challenge
#: visualisers (barrier orange, car blue, driveable surface magenta, vegetation green, ...);
#: ``free`` (17) is white and is drawn as background.
OCC3D_COLORS: tuple[tuple[int, int, int], ...] = (
    (0, 0, 0),  # others
    (255, 120, 50),  # barrier
    (255, 192, 203),  # bicycle
    (255, 255, 0),  # bus
    (0, 150, 245),  # car
    (0, 255, 255),  # construction_vehicle
    (200, 180, 0),  # motorcycle
    (255, 0, 0),  # pedestrian
    (255, 240, 150),  # traffic_cone
    (135, 60, 0),  # trailer
    (160, 32, 240),  # truck
    (255, 0, 255),  # driveable_surface
    (139, 137, 137),  # other_flat
    (75, 0, 75),  # sidewalk
    (150, 240, 80),  # terrain
    (230, 230, 250),  # manmade
    (0, 175, 0),  # vegetation
    (255, 255, 255),  # free
)

#: SemanticKITTI SSC colours indexed by id: the official ``color_map`` of the semantic-kitti-api
#: (``config/semantic-kitti.yaml``, stored there as BGR) converted to RGB through its
#: ``learning_map_inv``; ``empty`` (0) is black and is drawn as background.
SEMANTIC_KITTI_COLORS: tuple[tuple[int, int, int], ...] = (
    (0, 0, 0),  # empty
    (100, 150, 245),  # car
    (100, 230, 245),  # bicycle
    (30, 60, 150),  # motorcycle
    (80, 30, 180),  # truck
    (0, 0, 255),  # other-vehicle
    (255, 30, 30),  # person
    (255, 40, 200),  # bicyclist
    (150, 30, 90),  # motorcyclist
    (255, 0, 255),  # road
    (255, 150, 255),  # parking
    (75, 0, 75),  # sidewalk
    (175, 0, 75),  # other-ground
    (255, 200, 0),  # building
    (255, 120, 50),  # fence
    (0, 175, 0),  # vegetation
    (135, 60, 0),  # trunk
    (150, 240, 80),  # terrain
    (255, 240, 150),  # pole
    (255, 0, 0),  # traffic-sign
)


def class_colors(class_names: tuple[str, ...] | list[str]) -> tuple[tuple[int, int, int], ...]:
    """The colour of each class of a taxonomy, index = id.

    The Occ3D-nuScenes and SemanticKITTI taxonomies get their official palettes; any other list
    of names gets distinct, deterministic colours (evenly spaced hues), so a new data set is
    drawable without registering anything.
    """
    names = tuple(class_names)
    if names == OCC3D_CLASSES:
        return OCC3D_COLORS
    if names == SEMANTIC_KITTI_CLASSES:
        return SEMANTIC_KITTI_COLORS
    import colorsys

    out = []
    for i in range(len(names)):
        r, g, b = colorsys.hsv_to_rgb((i * 0.618033988749895) % 1.0, 0.75, 0.95)
        out.append((round(r * 255), round(g * 255), round(b * 255)))
    return tuple(out)
