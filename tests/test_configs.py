"""Every shipped config composes, validates and trains a couple of steps on the tiny world."""

import functools
from pathlib import Path

import pytest
import torch
import yaml

from occplug.config import compose, validate
from occplug.plugins import config_dirs, get_registry
from occplug.testing import run_config

ROOT = Path(__file__).resolve().parents[1]


def _plugin_files():
    files = []
    for name, folder in sorted(config_dirs().items()):
        if name != "occplug":  # the core's folder holds partial bases (trainer/, data/)
            files += sorted(Path(folder).rglob("*.yaml"))
    return files


# Collection asks for each file's composition several times (the recipe list twice, the real-data recipes' data
# type): each file is composed once per process.
@functools.cache
def _partial(path):
    """A plugin's overlay meant to be composed onto a recipe (e.g. duocc/anchors/synthetic): no data section."""
    return "data" not in compose([str(path)]).data


@functools.cache
def _data_type(path):
    """``data.type`` of the recipe ``path`` composed alone."""
    return compose([str(path)]).resolved()["data"]["type"]


def recipes():
    """Full configs (they have a model and a data section once composed): ./configs and plugin config dirs."""
    return sorted((ROOT / "configs").rglob("*.yaml")) + [p for p in _plugin_files() if not _partial(p)]


def test_core_bases_compose():
    for path in sorted(Path(config_dirs()["occplug"]).rglob("*.yaml")):
        assert isinstance(yaml.safe_load(path.read_text()), dict), path
        compose([str(path)])


def test_plugin_overlays_compose():
    """Partial plugin configs compose on their own; the recipes that use them as a base train below."""
    overlays = [p for p in _plugin_files() if _partial(p)]
    assert overlays  # duocc/anchors/synthetic at least
    for path in overlays:
        assert isinstance(yaml.safe_load(path.read_text()), dict), path
        compose([str(path)])


@pytest.mark.parametrize("path", recipes(), ids=lambda p: p.stem)
def test_recipe_validates_and_trains(path, tmp_path):
    cfg = compose([str(path)]).resolved()
    if cfg["data"]["type"] != "synthetic":  # a recipe for a real data set (and its weights) composes here only
        assert cfg["model"] and cfg["data"]["root"]
        return
    validate(cfg, get_registry())
    metrics = run_config(str(path), run_dir=tmp_path / "run")
    assert metrics and all(v == v for k, v in metrics.items() if k in ("mIoU", "IoU"))  # computed, not NaN


@pytest.mark.parametrize("view_transform", ["lss", "backward_projection"])
def test_view_transform_ablation_swaps_with_one_override(view_transform, tmp_path):
    cfg = compose([str(ROOT / "configs" / "baseline.yaml")], [f"model.view_transform.type={view_transform}"]).resolved()
    assert cfg["model"]["view_transform"]["type"] == view_transform
    assert "grid" not in cfg["model"]["view_transform"]  # given by the model: either view transform gets the run's
    metrics = run_config(
        str(ROOT / "configs" / "baseline.yaml"),
        run_dir=tmp_path / "run",
        overrides=[f"model.view_transform.type={view_transform}"],
    )
    assert metrics["IoU"] >= 0


def _real_recipes():
    """Each real-data recipe, and the baseline on each real data set (README, "Real data sets"), as config lists."""
    files = [[str(p)] for p in recipes() if _data_type(p) != "synthetic"]
    baseline = str(ROOT / "configs" / "baseline.yaml")
    return files + [[baseline, "occplug/data/occ3d_nuscenes"], [baseline, "occplug/data/semantickitti"]]


@pytest.mark.parametrize("refs", _real_recipes(), ids=lambda refs: "+".join(Path(r).stem for r in refs))
def test_a_real_recipe_s_image_size_fits_its_own_encoder(refs):
    """A recipe for a real data set trains only on a GPU, so the suite does not train it; but its image size must
    suit its own encoder (``occle/semantickitti`` once asked 370 x 1220 of a stride-8 encoder), in every phase."""
    from occplug.config.phases import phase_specs

    cfg = compose(refs).resolved()
    configs = [spec.config for spec in phase_specs(cfg)] if cfg.get("phases") else [cfg]
    for config in configs:
        spec = dict(config["model"]["encoder"])
        if spec["type"] == "timm":  # CI installs timm (the dev extras): the real backbone, random weights
            spec["weights"] = None
        with torch.device("meta"):  # strides only: no memory, no random init of ConvNeXt-B's 88M weights
            encoder = get_registry().build("encoder", spec)
        height, width = config["data"]["image_size"]
        stride = max(encoder.level_strides)
        assert height % stride == 0 and width % stride == 0, (refs, (height, width), stride)
