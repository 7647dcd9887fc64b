"""Nested settings (``occplug.config.settings``): a component argument that is a group of settings.

The core's validator checks a group like a component's own arguments -- keys (did-you-mean), types and
``Annotated`` rules, at any depth, naming the full dotted key in one line -- and the builder hands the component
the typed object. Checked on a toy component and on DuOcc's ``query_agg`` (with its ``detector`` and
``selection`` groups), the group that used to be re-validated by hand.
"""

from __future__ import annotations

import collections.abc as cabc
import dataclasses
import inspect
import types
import typing
from pathlib import Path
from typing import Annotated, Literal

import pytest
import torch
from torch import Tensor, nn
from toy_plugin import ToyPlugin

import occplug
from occplug.cli import main
from occplug.config import ConfigError, make_settings, settings, validate
from occplug.constraints import Positive, UnitInterval

DUOCC_CONFIGS = Path(__file__).resolve().parents[2] / "plugins" / "occplug_duocc" / "configs"


# ---------------------------------------------------------------------------------------------- the mechanism


@settings
class Inner:
    depth: Annotated[int, Positive] = 2
    sizes: tuple[Annotated[float, Positive], ...] = (1.0, 2.0)


@settings
class Outer:
    rate: Annotated[float, UnitInterval] = 0.5
    mode: Literal["a", "b"] = "a"
    inner: Inner = Inner()
    required: str


class GroupedEncoder(occplug.ImageEncoder):
    """A toy encoder taking a group of settings (kept, to look at what the builder passed)."""

    def __init__(self, channels: Annotated[int, Positive] = 4, group: Outer | None = None) -> None:
        super().__init__()
        self.out_channels, self.stride, self.group = channels, 1, group
        self.conv = nn.Conv2d(3, channels, 1)

    def forward(self, images: Tensor) -> Tensor:
        return self.conv(images.flatten(0, 1)).unflatten(0, images.shape[:2])


class _Plugin:
    @occplug.hookimpl
    def occplug_register_components(self, registry: occplug.Registry) -> None:
        registry.add("encoder", "grouped", GroupedEncoder)


@pytest.fixture
def reg(isolated_registry):
    return isolated_registry(plugins=[("toy", ToyPlugin()), ("grouped", _Plugin())])


def _cfg(group):
    encoder = {"type": "grouped", "group": group}
    return {"data": {"type": "synthetic", "preset": "tiny"}, "model": {"type": "toy_model", "encoder": encoder}}


@pytest.mark.parametrize(
    ("group", "line"),
    [
        ({"required": "x", "rat": 0.1}, "model.encoder.group.rat: Outer has no setting 'rat'; did you mean 'rate'?"),
        (
            {"required": "x", "inner": {"dept": 3}},
            "model.encoder.group.inner.dept: Inner has no setting 'dept'; did you mean 'depth'?",
        ),
        ({"required": "x", "rate": 1.5}, "model.encoder.group.rate: expected a number in [0, 1], got float 1.5"),
        ({"required": "x", "mode": "c"}, "model.encoder.group.mode: expected one of 'a', 'b', got str 'c'"),
        (
            {"required": "x", "inner": {"sizes": [1.0, -1.0]}},
            "model.encoder.group.inner.sizes: expected every element a number > 0, got list [1.0, -1.0]",
        ),
        ({"required": "x", "inner": 3}, "model.encoder.group.inner: expected a mapping of Inner, got int 3"),
        ({"rate": 0.1}, "model.encoder.group: Outer is missing required setting(s): required"),
        (7, "model.encoder.group: expected a mapping of Outer or null, got int 7"),
    ],
)
def test_the_validator_checks_a_group_of_settings_in_one_line_naming_the_dotted_key(reg, group, line):
    with pytest.raises(ConfigError) as caught:
        validate(_cfg(group), reg)
    assert str(caught.value) == line


def test_a_valid_group_validates_and_reaches_the_component_as_its_typed_object(reg):
    group = {"required": "x", "rate": 0.25, "inner": {"sizes": [3.0]}}
    validate(_cfg(group), reg)
    built = reg.build("encoder", {"type": "grouped", "group": group})
    assert built.group == Outer(required="x", rate=0.25, inner=Inner(sizes=(3.0,)))
    assert isinstance(built.group.inner, Inner) and built.group.inner.sizes == (3.0,)  # a list became the tuple
    assert reg.build("encoder", {"type": "grouped"}).group is None
    same = Outer(required="y")
    assert reg.build("encoder", {"type": "grouped", "group": same}).group is same  # an object passes as it is
    with pytest.raises(dataclasses.FrozenInstanceError):
        built.group.rate = 1.0  # type: ignore[misc]


def test_make_settings_builds_nested_groups():
    made = make_settings(Outer, {"required": "z", "inner": {"depth": 5}})
    assert made == Outer(required="z", inner=Inner(depth=5)) and made.rate == 0.5


# ---------------------------------------------------------------------------------------------- DuOcc's query_agg


def _cli(capsys, *argv: str) -> tuple[int, list[str]]:
    code = main(list(argv))
    return code, [line for line in capsys.readouterr().err.splitlines() if line.strip()]


TYPOS = [
    (
        "model.scene.query_agg.score_treshold=0.5",
        "error: model.scene.query_agg.score_treshold: QueryAggSettings has no setting 'score_treshold'; "
        "did you mean 'score_threshold'?",
    ),
    (
        "model.scene.query_agg.detector.num_querys=16",
        "error: model.scene.query_agg.detector.num_querys: DetectorSettings has no setting 'num_querys'; "
        "did you mean 'num_queries'?",
    ),
    (
        "model.scene.query_agg.selection={iou_treshold: 0.2}",
        "error: model.scene.query_agg.selection.iou_treshold: SelectionSettings has no setting 'iou_treshold'; "
        "did you mean 'iou_threshold'?",
    ),
]


@pytest.mark.parametrize(("override", "line"), TYPOS)
def test_a_typo_inside_query_agg_is_one_did_you_mean_line_from_config_validate(capsys, override, line):
    code, err = _cli(capsys, "config", "validate", "-c", "duocc/full", override)
    assert code == 2
    assert err == [line]


def test_a_typo_inside_query_agg_stops_fit_before_anything_is_written(capsys, tmp_path):
    run_dir = tmp_path / "run"
    code, err = _cli(
        capsys, "fit", "-c", "duocc/full", "-c", "occplug/trainer/debug", "--run-dir", str(run_dir), TYPOS[1][0]
    )
    assert code == 2
    assert err == [TYPOS[1][1]]
    assert not run_dir.exists()


@pytest.mark.parametrize(
    ("override", "line"),
    [
        # these trained silently before: no query is ever selected (DQA writes nothing: D quietly becomes C) ...
        ("model.scene.query_agg.max_queries=0", "model.scene.query_agg.max_queries: expected an int > 0, got int 0"),
        (
            "model.scene.query_agg.score_threshold=1.5",
            "model.scene.query_agg.score_threshold: expected a number < 1, got float 1.5",
        ),
        # ... the voxel FFN silently fell back to 4 x channels ...
        ("model.scene.query_agg.ffn_hidden=0", "model.scene.query_agg.ffn_hidden: expected an int > 0, got int 0"),
        # ... label id -1 indexed the lookup from its end (label 0 became detection class 0) ...
        (
            "model.scene.query_agg.detection_classes=[-1]",
            "model.scene.query_agg.detection_classes: expected every element an int >= 0, got list [-1]",
        ),
        # ... and a cached instance's confidence grew frame by frame
        (
            "model.scene.query_agg.detector.confidence_decay=2.0",
            "model.scene.query_agg.detector.confidence_decay: expected a number in [0, 1], got float 2.0",
        ),
    ],
)
def test_an_out_of_range_value_inside_query_agg_is_one_line(capsys, override, line):
    code, err = _cli(capsys, "config", "validate", "-c", "duocc/full", override)
    assert code == 2
    assert err == [f"error: {line}"]


def test_query_agg_reaches_the_scene_as_typed_settings(monkeypatch):
    from occplug.run import runner
    from occplug_duocc import scene as duocc_scene
    from occplug_duocc.blocks.queryagg import DetectorSettings, QueryAggSettings, SelectionSettings

    seen = []
    real = duocc_scene.QueryAggregation

    def spy(channels, grid, level_channels, config):
        seen.append((list(level_channels), config))
        return real(channels, grid, level_channels, config)

    monkeypatch.setattr(duocc_scene, "QueryAggregation", spy)
    cfg = runner.load_config(
        ["duocc/full", "occplug/trainer/debug"],
        [
            "grid.range=[-8.0,-8.0,-1.0,8.0,8.0,5.4]",
            "model.encoder.out_channels=16",
            "model.scene.query_agg.max_queries=5",
            "model.scene.query_agg.detector.num_layers=1",
            "model.scene.query_agg.selection={iou_threshold: 0.2}",
        ],
    )
    _, model = runner.build_run(cfg)
    [(levels, config)] = seen
    assert isinstance(config, QueryAggSettings) and isinstance(config.detector, DetectorSettings)
    assert config.max_queries == 5 and config.detector.num_layers == 1 and config.detector.num_queries == 48
    assert config.selection == SelectionSettings(iou_threshold=0.2)
    assert config.detection_classes == tuple(range(1, 11))  # a list in the YAML, a tuple in the settings
    qa = model.scene.query_agg
    assert qa.max_queries == 5 and len(qa.detector.layers) == 1 and qa.rule["iou_threshold"] == 0.2
    # level_channels are handed down (given) from the encoder, not wired back by interpolation in the configs
    assert levels == list(model.encoder.level_channels) == [16, 16]
    for layer in qa.detector.layers:
        projections = layer.deformable.level_proj
        assert len(projections) == 2 and all(isinstance(p, nn.Identity) or p.in_features == 16 for p in projections)
    assert torch.is_tensor(qa.detector.anchors)


def test_no_duocc_config_wires_level_channels_back_by_interpolation():
    wired = [p.name for p in DUOCC_CONFIGS.rglob("*.yaml") if "level_channels" in p.read_text()]
    assert not wired, wired


# ---------------------------------------------------------------------------------------------- every group


def _groups():
    """``(kind, component, dotted key, settings class)`` of every settings group of every registered component."""
    from occplug.plugins import get_registry
    from occplug.settings import settings_type
    from occplug.slots import component_params

    def walk(kind, name, key, cls):
        yield kind, name, key, cls
        for field, (_, annotation) in component_params(cls).items():
            inner = settings_type(annotation)
            if inner is not None:
                yield from walk(kind, name, f"{key}.{field}", inner)

    for entry in get_registry().entries():
        for key, (_, annotation) in component_params(entry.factory).items():
            cls = settings_type(annotation)
            if cls is not None:
                yield from walk(entry.kind, entry.name, key, cls)


def _numeric_or_list(annotation) -> bool:
    """Whether an annotation admits a number or a list (through ``Annotated`` and unions)."""
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _numeric_or_list(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        return any(_numeric_or_list(a) for a in typing.get_args(annotation))
    return annotation in (int, float, list, tuple) or origin in (list, tuple, cabc.Sequence)


def _rules(annotation):
    """``(rule, on_elements)`` of every constraint declared on a field and on its list's elements."""
    from occplug.constraints import _element_annotation, constraints_of

    element = _element_annotation(annotation)
    return [(r, False) for r in constraints_of(annotation)] + [
        (r, True) for r in (constraints_of(element) if element is not None else [])
    ]


def test_every_numeric_or_list_setting_declares_a_rule_and_every_rule_is_one_line():
    from occplug.config.validate import _Validator
    from occplug.constraints import Length, violated
    from occplug.plugins import get_registry
    from occplug.slots import component_params

    groups = list(_groups())
    assert {("scene", "duocc_stream", "query_agg"), ("scene", "duocc_stream", "query_agg.detector")} <= {
        g[:3] for g in groups
    }
    cases, offenders = 0, []
    for kind, name, key, cls in groups:
        for field, (param, annotation) in component_params(cls).items():
            rules = _rules(annotation)
            if param.default is not inspect.Parameter.empty:  # the defaults keep their behaviour: they pass
                default = param.default
                assert violated(list(default) if isinstance(default, tuple) else default, annotation) is None, field
            if _numeric_or_list(annotation) and not rules:
                offenders.append(f"{name}.{key}.{field}: {annotation}")
                continue
            length = next((r for r, on_elements in rules if isinstance(r, Length) and not on_elements), None)
            n = 1 if length is None else (length.exact if length.exact is not None else max(length.min or 1, 1))
            for rule, on_elements in rules:
                for bad in rule.violations():
                    value = [bad] * n if on_elements else bad
                    node: dict = {field: value}
                    for part in reversed(key.split(".")[1:]):
                        node = {part: node}
                    with pytest.raises(ConfigError) as caught:
                        _Validator(get_registry()).node({"type": name, key.split(".")[0]: node}, kind, "x")
                    message = str(caught.value)
                    assert message.startswith(f"x.{key}.{field}: expected "), message
                    assert "\n" not in message
                    cases += 1
    assert not offenders, offenders
    assert cases >= 40, cases
