"""DuOcc's recipes composed and validated: the real-data ones with the paper's settings, the synthetic ones' class
weights (the synthetic recipes train in tests/test_configs.py's sweep)."""

from __future__ import annotations

import ast
import copy
from importlib.resources import files

from occplug.config import compose, validate
from occplug.plugins import get_registry

#: timm is optional (not in the dev extra): the recipe is validated with a core encoder in its slot.
CORE_ENCODER = "model.encoder={type: small_cnn, out_channels: 64, stride: 16}"
LOSSES = ("occupancy", "forecast", "occupied")


def test_occ3d_nuscenes_has_the_papers_settings_and_validates():
    cfg = compose(["duocc/occ3d_nuscenes"]).resolved()
    model = cfg["model"]
    assert cfg["data"]["type"] == "occ3d_nuscenes" and cfg["data"]["image_size"] == [256, 704]
    assert cfg["grid"] == {"range": [-40.0, -40.0, -1.0, 40.0, 40.0, 5.4], "voxel_size": 0.4}  # 200 x 200 x 16
    assert "grid" not in model["view_transform"] and "grid" not in model["scene"]  # both given the run's grid
    assert model["encoder"] == {
        "type": "timm",
        "model_name": "resnet50",
        "out_channels": 64,
        "feature_level": 3,
        "weights": None,
    }
    assert model["view_transform"]["out_channels"] == 64  # V_init: 200 x 200 x 16 x 64
    detector = model["scene"]["query_agg"]["detector"]
    cw = model["supervision"]["occupancy"]["class_weights"]  # the code's: others .. vegetation, free (halved)
    assert len(cw) == 18 and cw[4] == 0.300 and cw[-1] == 0.117 and min(cw[:-1]) == 0.263
    assert model["supervision"]["occupancy"]["normalize"] == "count"  # the code's: over the visible voxels
    # not the synthetic world's 48 k-means anchors of duocc/full: uniform until the user makes the data's own
    assert detector["anchor_centres"] is None and detector["anchor_size"] == [4.0, 1.8, 1.6]
    assert (detector["num_queries"], detector["num_layers"]) == (900, 6)
    assert (detector["num_dn_groups"], detector["max_dn_gt"]) == (5, 32)  # the code's Sparse4D v3 denoising
    weights = {name: model["supervision"][name]["weight"] for name in ("depth", *LOSSES, "detection", "mask")}
    assert weights == {
        "depth": 0.05,
        "occupancy": 10.0,
        "forecast": 10.0,
        "occupied": 10.0,
        "detection": 0.2,
        "mask": 1.0,
    }  # suppl. A.4
    mask = model["supervision"]["mask"]
    assert (mask["num_queries"], mask["num_groups"], mask["camera_mask"]) == (100, 6, True)
    assert all(model["supervision"][name]["camera_mask"] for name in LOSSES)
    assert cfg["optimizer"]["lr"] == 0.0002 and cfg["optimizer"]["reference_batch"] == 8
    assert cfg["trainer"]["max_epochs"] == 24 and cfg["trainer"]["gradient_clip_val"] == 5.0
    validate(compose(["duocc/occ3d_nuscenes"], [CORE_ENCODER]).resolved(), get_registry())


def test_rayiou_recipe_is_the_occ3d_recipe_without_the_camera_mask():
    masked = compose(["duocc/occ3d_nuscenes"]).resolved()
    unmasked = compose(["duocc/occ3d_nuscenes_rayiou"]).resolved()
    assert unmasked["metrics"] == ["rayiou"] and unmasked["eval_mask"] == "none"
    assert not any(unmasked["model"]["supervision"][name]["camera_mask"] for name in (*LOSSES, "mask"))
    expected = copy.deepcopy(masked)
    for name in (*LOSSES, "mask"):
        expected["model"]["supervision"][name]["camera_mask"] = False
    expected["metrics"], expected["eval_mask"] = ["rayiou"], "none"
    assert unmasked == expected  # nothing else changes
    validate(compose(["duocc/occ3d_nuscenes_rayiou"], [CORE_ENCODER]).resolved(), get_registry())


def test_synthetic_no_camera_mask_recipe_is_full_without_the_mask():
    full = compose(["duocc/full"]).resolved()
    unmasked = compose(["duocc/no_camera_mask"]).resolved()
    for name in LOSSES:
        full["model"]["supervision"][name]["camera_mask"] = False
    assert unmasked["model"] == full["model"] and unmasked["eval_mask"] == "none"
    assert [m if isinstance(m, str) else m["type"] for m in unmasked["metrics"]] == ["occ3d_miou", "rayiou"]


def test_synthetic_recipes_weight_the_occupancy_ce_by_the_default_worlds_counts():
    from occplug_duocc.tools.class_weights import duocc_class_weights

    overlay = compose(["duocc/class_weights/synthetic"]).resolved()["model"]["supervision"]["occupancy"]
    # the overlay's header records the counts it was made from: the weights are the code's rule over them
    text = (files("occplug_duocc") / "configs" / "class_weights" / "synthetic.yaml").read_text()
    counts = ast.literal_eval(next(ln[2:] for ln in text.splitlines() if ln.startswith("# [")))
    assert len(counts) == 18 and counts[4] > 0  # car voxels
    assert overlay["class_weights"] == [round(float(w), 3) for w in duocc_class_weights(counts)]
    for recipe in ("single_frame", "stream_agg", "stacking", "full", "full_mask"):
        occupancy = compose([f"duocc/{recipe}"]).resolved()["model"]["supervision"]["occupancy"]
        assert occupancy["class_weights"] == overlay["class_weights"], recipe
    # the real-data recipe keeps the code's nuScenes weights
    nusc = compose(["duocc/occ3d_nuscenes"]).resolved()["model"]["supervision"]["occupancy"]["class_weights"]
    assert nusc[-1] == 0.117 and nusc != overlay["class_weights"]


def test_the_detector_settings_default_to_the_detectors_own_defaults():
    """``query_agg.detector`` left out builds the same detector as :class:`SparseDetector`'s defaults (its
    ``anchor_range`` excepted: left out, it is the scene's grid range, and ``num_classes`` / ``level_channels``,
    which the scene gives)."""
    import dataclasses
    import inspect

    from occplug_duocc.blocks.detector import SparseDetector
    from occplug_duocc.blocks.queryagg import DetectorSettings

    params = inspect.signature(SparseDetector).parameters
    given = {"num_classes", "level_channels"}
    assert {f.name for f in dataclasses.fields(DetectorSettings)} == set(params) - given
    for field in dataclasses.fields(DetectorSettings):
        if field.name != "anchor_range":
            default = params[field.name].default
            assert field.default == (tuple(default) if isinstance(default, list) else default), field.name


def test_the_detector_pretraining_phase_trains_detection_alone_and_hands_its_detector_on():
    from occplug.config import phase_specs
    from occplug.run import runner

    detector, full = phase_specs(runner.load_config(["duocc/detector_pretrain"], []))
    assert (detector.name, full.name) == ("detector", "full")
    assert set(detector.config["model"]["supervision"]) == {"detection"}
    assert detector.config["model"]["supervision"]["detection"]["weight"] == 1.0
    assert set(full.config["model"]["supervision"]) >= {"detection", "occupancy", "depth", "forecast", "occupied"}
    (source,) = full.init_from
    assert source.phase == "detector" and set(source.prefixes) == {"model.encoder", "model.scene.query_agg.detector"}
