"""DuOcc's detection classes come from the run's class names, and a wrong one stops a run before anything is written.

Left out, ``query_agg.detection_classes`` is the data's ``dynamic`` class group, by name
(:func:`occplug.data.class_groups`): the same ids as the former hard-coded list on Occ3D and the default world.
An id the data set lacks, or a choice outside its ``Literal`` (``fusion``), is one ``error:`` line from
``occplug config validate`` and from ``occplug fit`` (exit 2, no run directory).
"""

import pytest

from occplug.cli import main
from occplug.data import (
    OCC3D_CLASSES,
    SEMANTIC_KITTI_CLASSES,
    SEMANTIC_KITTI_DYNAMIC,
    Occ3DNuScenesDataModule,
    SemanticKITTIDataModule,
)
from occplug.data.synthetic import SyntheticDataModule
from occplug.run import runner
from occplug_duocc.blocks.queryagg import (
    DEFAULT_DETECTION_CLASSES,
    DEFAULT_SMALL_CLASSES,
    QueryAggregation,
    QueryAggSettings,
    resolve_detection_classes,
)
from occplug_duocc.scene import DuOccStream

#: the ids the detector classified before they came from the class names (barrier ... truck on Occ3D)
FORMER_IDS = (1, 2, 3, 4, 5, 6, 7, 8, 9, 10)
#: the ids the selection's small-object rule read before they came from the class names
FORMER_SMALL_IDS = (1, 2, 6, 7, 8)


def _cli(capsys, *argv: str) -> tuple[int, list[str]]:
    code = main(list(argv))
    return code, [line for line in capsys.readouterr().err.splitlines() if line.strip()]


def test_the_default_world_and_occ3d_keep_their_detection_ids():
    assert DEFAULT_DETECTION_CLASSES == FORMER_IDS
    for module in (SyntheticDataModule, Occ3DNuScenesDataModule):
        assert module.class_names == OCC3D_CLASSES
        assert resolve_detection_classes(QueryAggSettings(), module.class_names).detection_classes == FORMER_IDS


def test_the_detection_classes_are_the_dynamic_group_by_name():
    """On SemanticKITTI the same rule names other ids: its eight movable classes."""
    resolved = resolve_detection_classes(QueryAggSettings(), SemanticKITTIDataModule.class_names)
    assert [SEMANTIC_KITTI_CLASSES[i] for i in resolved.detection_classes] == list(SEMANTIC_KITTI_DYNAMIC)


def test_given_detection_classes_are_checked_against_the_run_and_kept():
    given = QueryAggSettings(detection_classes=(4, 10), small_classes=(4,))
    assert resolve_detection_classes(given, OCC3D_CLASSES) is given
    with pytest.raises(ValueError, match=r"^duocc_stream query_agg.detection_classes: label id 18 is not one of the "):
        resolve_detection_classes(QueryAggSettings(detection_classes=(4, 18)), OCC3D_CLASSES)
    with pytest.raises(ValueError, match="no taxonomy with a 'dynamic' class group"):
        resolve_detection_classes(QueryAggSettings(), ("free", "thing"))
    assert resolve_detection_classes(QueryAggSettings(), None).detection_classes is None  # outside a run: as given


def test_the_small_objects_are_named_and_keep_their_ids_on_occ3d():
    """``small_objects`` is barrier, bicycle, motorcycle, pedestrian and traffic cone by name (and SemanticKITTI's
    person and riders): the former ids on Occ3D and the default world, SemanticKITTI's own, Occ3D's outside a run;
    a taxonomy with none of the names is one line, not a silently empty set."""
    assert DEFAULT_SMALL_CLASSES == FORMER_SMALL_IDS
    for module in (SyntheticDataModule, Occ3DNuScenesDataModule):
        assert resolve_detection_classes(QueryAggSettings(), module.class_names).small_classes == FORMER_SMALL_IDS
    kitti = resolve_detection_classes(QueryAggSettings(), SemanticKITTIDataModule.class_names).small_classes
    assert [SEMANTIC_KITTI_CLASSES[i] for i in kitti] == [
        "bicycle",
        "motorcycle",
        "person",
        "bicyclist",
        "motorcyclist",
    ]
    assert resolve_detection_classes(QueryAggSettings(), None).small_classes == FORMER_SMALL_IDS
    assert resolve_detection_classes(QueryAggSettings(small_classes=None), OCC3D_CLASSES).small_classes is None
    with pytest.raises(ValueError, match=r"^duocc_stream query_agg.small_classes: small_objects names none of the run"):
        resolve_detection_classes(QueryAggSettings(detection_classes=(1,)), ("free", "car", "tree"))


def test_the_built_full_model_detects_the_dynamic_group(model_dm):
    cfg = runner.load_config(["duocc/full"])
    assert "detection_classes" not in cfg["model"]["scene"]["query_agg"]  # no hard-coded ids in the recipe
    model, _ = model_dm
    assert isinstance(model.scene, DuOccStream) and isinstance(model.scene.query_agg, QueryAggregation)
    assert model.scene.query_agg.classes == FORMER_IDS
    small = [FORMER_IDS[i] for i in model.scene.query_agg.rule["small_classes"]]
    assert small == list(FORMER_SMALL_IDS)  # detection class indices of the small objects, by name


@pytest.mark.parametrize(
    ("override", "line"),
    [
        (
            "model.scene.query_agg.detection_classes=[99]",
            "error: model.scene.query_agg.detection_classes: expected label ids of the data set's 18 classes "
            "(0 to 17), got list [99]",
        ),
        (
            "model.scene.query_agg.small_classes=[1, 18]",
            "error: model.scene.query_agg.small_classes: expected label ids of the data set's 18 classes "
            "(0 to 17), got list [1, 18]",
        ),
        ("model.scene.fusion=sum", "error: model.scene.fusion: expected one of 'add', 'concat', got str 'sum'"),
        (
            "model.scene.fusion=concatt",
            "error: model.scene.fusion: expected one of 'add', 'concat', got str 'concatt'; did you mean 'concat'?",
        ),
    ],
)
def test_a_wrong_class_or_choice_is_one_line_before_anything_is_written(capsys, tmp_path, override, line):
    code, err = _cli(capsys, "config", "validate", "-c", "duocc/full", override)
    assert (code, err) == (2, [line])
    run_dir = tmp_path / "run"
    code, err = _cli(
        capsys, "fit", "-c", "duocc/full", "-c", "occplug/trainer/debug", "--run-dir", str(run_dir), override
    )
    assert (code, err) == (2, [line])
    assert not run_dir.exists()
