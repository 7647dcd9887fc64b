import textwrap

import pytest
from toy_plugin import ToyPlugin

from occplug.config import ConfigError, compose, validate


@pytest.fixture
def reg(isolated_registry):
    return isolated_registry(plugins=[("toy", ToyPlugin())])


def write(path, text):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(text))
    return path


def base_cfg(**model):
    return {"data": {"type": "synthetic", "preset": "tiny"}, "model": {"type": "toy_model", **model}}


def test_bases_merge_depth_first_then_body_then_overrides(tmp_path, reg):
    write(tmp_path / "a.yaml", "x: {a: 1, b: 1}\nl: [1, 2]\n")
    write(tmp_path / "b.yaml", "base: [a.yaml]\nx: {b: 2, c: 2}\n")
    write(tmp_path / "top.yaml", "base: [b]\nx: {c: 3}\nl: [9]\n")
    extra = write(tmp_path / "extra.yaml", "x: {d: 4}\n")
    out = compose([str(tmp_path / "top.yaml"), str(extra)], ["x.a=10", "l=[7, 8]"])
    assert out.data["x"] == {"a": 10, "b": 2, "c": 3, "d": 4}
    assert out.data["l"] == [7, 8]  # lists replace
    assert out.sources["x.b"].endswith("b.yaml") and out.sources["x.a"] == "override x.a=10"


def test_circular_base_is_an_error(tmp_path, reg):
    write(tmp_path / "a.yaml", "base: [b.yaml]\n")
    write(tmp_path / "b.yaml", "base: [a.yaml]\n")
    with pytest.raises(ConfigError, match="circular base"):
        compose([str(tmp_path / "a.yaml")])


def test_missing_file_and_bad_yaml(tmp_path, reg):
    with pytest.raises(ConfigError, match="config 'nope/nothing' not found"):
        compose(["nope/nothing"])
    bad = write(tmp_path / "bad.yaml", "a: [1, 2\n")
    with pytest.raises(ConfigError, match=r"bad.yaml:.*invalid YAML"):
        compose([str(bad)])


def test_plugin_config_dir_reference(reg):
    out = compose(["occplug/trainer/debug"])
    assert out.data["trainer"]["max_steps"] == 2


def test_project_configs_by_name(tmp_path, monkeypatch, reg):
    write(tmp_path / "configs" / "exp.yaml", "seed: 3\n")
    monkeypatch.chdir(tmp_path)
    assert compose(["exp"]).data["seed"] == 3


def test_type_change_drops_stale_arguments_keeps_accepted(reg):
    start = base_cfg(encoder={"type": "toy_encoder", "channels": 8, "scale": 2.0})
    out = compose([], ["model.encoder.type=other_encoder"], data=start)
    assert out.data["model"]["encoder"] == {"type": "other_encoder", "channels": 8}
    validate(out.resolved(), reg)
    same = compose([], ["model.encoder.type=toy_encoder", "model.encoder.scale=3"], data=start)
    assert same.data["model"]["encoder"] == {"type": "toy_encoder", "channels": 8, "scale": 3}


def test_type_change_in_a_later_file_replaces_node(tmp_path, reg):
    first = write(
        tmp_path / "one.yaml", "model: {type: toy_model, encoder: {type: toy_encoder, channels: 4, scale: 2.0}}\n"
    )
    second = write(tmp_path / "two.yaml", "model: {encoder: {type: other_encoder, depth: 5}}\n")
    out = compose([str(first), str(second)])
    assert out.data["model"]["encoder"] == {"type": "other_encoder", "channels": 4, "depth": 5}


def test_delete_override(reg):
    out = compose([], ["~model.lr"], data=base_cfg(lr=0.5, encoder={"type": "toy_encoder", "channels": 1}))
    assert "lr" not in out.data["model"]
    with pytest.raises(ConfigError, match="no key 'model.nope' to delete"):
        compose([], ["~model.nope"], data=base_cfg())


def test_malformed_override(reg):
    with pytest.raises(ConfigError, match="expected key=value"):
        compose([], ["model.lr"], data=base_cfg())


@pytest.mark.parametrize(
    ("model", "message"),
    [
        (
            {"encoder": {"type": "toy_encoder", "chanels": 8}},
            "model.encoder.chanels: toy_encoder (encoder, plugin toy) has no parameter 'chanels'; did you mean 'channels'?",
        ),
        (
            {"encoder": {"type": "toy_encoder"}},
            "model.encoder: toy_encoder (encoder, plugin toy) is missing required argument(s): channels",
        ),
        (
            {"encoder": {"type": "toy_encoder", "channels": "eight"}},
            "model.encoder.channels: expected int, got str 'eight'",
        ),
        (
            {"encoder": {"type": "toy_encoder", "channels": 8, "scale": True}},
            "model.encoder.scale: expected float, got bool True",
        ),
        (
            {"encoder": {"type": "toy_encoder", "channels": 8, "mode": "c"}},
            "model.encoder.mode: expected one of 'a', 'b', got str 'c'",
        ),
        (
            {"encoder": {"type": "toy_encodr", "channels": 8}},
            "model.encoder.type: no encoder named 'toy_encodr'; did you mean 'toy_encoder'?",
        ),
        ({"encoder": {"channels": 8}}, "model.encoder: missing 'type:' naming a registered encoder"),
        (
            {
                "encoder": {"type": "toy_encoder", "channels": 8},
                "extras": {"e1": {"type": "toy_encoder", "channels": 1, "scal": 1.0}},
            },
            "model.extras.e1.scal: toy_encoder (encoder, plugin toy) has no parameter 'scal'; did you mean 'scale'?",
        ),
        (
            {"encodr": {"type": "toy_encoder", "channels": 8}},
            "model.encodr: toy_model (model, plugin toy) has no parameter 'encodr'; did you mean 'encoder'?",
        ),
    ],
)
def test_validation_errors_name_the_key(reg, model, message):
    with pytest.raises(ConfigError) as err:
        validate(base_cfg(**model), reg)
    assert str(err.value).startswith(message)
    assert "\n" not in str(err.value)


def test_validation_of_sections(reg):
    good = base_cfg(encoder={"type": "toy_encoder", "channels": 8})
    validate({**good, "optimizer": {"type": "adamw", "lr": 0.1}, "trainer": {"max_epochs": 2}}, reg)
    cases = [
        ({"modle": {}}, "modle: unknown top-level section; did you mean 'model'?"),
        ({"optimizer": {"type": "adamww"}}, "optimizer.type: unknown optimizer 'adamww'; did you mean 'adamw'?"),
        ({"optimizer": {"type": "adamw", "lr": "fast"}}, "optimizer.lr: expected"),
        ({"trainer": {"max_epoch": 2}}, "trainer.max_epoch: unknown trainer argument; did you mean 'max_epochs'?"),
        ({"grid": {"range": [0, 0, 0, 1, 1, 1], "voxel_size": 0.3}}, "grid: grid extent on axis x"),
        (
            {"scheduler": {"type": "cosine", "warmup": 5}},
            "scheduler.warmup: unknown scheduler argument; did you mean 'warmup_steps'?",
        ),
    ]
    for extra, message in cases:
        with pytest.raises(ConfigError) as err:
            validate({**good, **extra}, reg)
        assert str(err.value).startswith(message), str(err.value)


def test_interpolation_shares_grid(reg):
    data = {**base_cfg(), "grid": {"range": [0, 0, 0, 2, 2, 2], "voxel_size": 1.0}}
    data["data"]["grid"] = "${grid}"
    assert compose([], ["grid.voxel_size=0.5"], data=data).resolved()["data"]["grid"]["voxel_size"] == 0.5
    data["data"]["grid"] = "${gird}"
    with pytest.raises(ConfigError, match="gird"):
        compose([], [], data=data).resolved()
