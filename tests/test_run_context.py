"""One builder (``Registry.build``) and one run context (``occplug.RunContext``), built once by the runner."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from torch import Tensor, nn

import occplug
from occplug.components import DenseVoxels, VoxelClassifier
from occplug.data.classes import OCC3D_CLASSES, OCC3D_DYNAMIC
from occplug.errors import ComponentArgumentError
from occplug.geometry import GridSpec
from occplug.interfaces import Head, SceneRepresentation
from occplug.registry import Registry
from occplug.run import runner

BASELINE = "configs/baseline.yaml"
SMALL = ["occplug/trainer/debug"]
GRID = GridSpec((-2.0, -2.0, 0.0, 2.0, 2.0, 1.0), 0.5)
SEEN: list[occplug.RunContext] = []


class ContextScene(DenseVoxels):
    """The dense-voxel scene, asking for the run context and building a nested head through it."""

    def __init__(self, in_channels: int, context: occplug.RunContext, out_channels: int = 8) -> None:
        super().__init__(in_channels, out_channels=out_channels, num_blocks=0)
        SEEN.append(context)
        self.dynamic = context.ids("dynamic")
        self.refine = context.build(
            "head", {"type": "toy_context_head"}, in_channels=out_channels, num_classes=context.num_classes
        )


class ContextHead(VoxelClassifier):
    def __init__(self, in_channels: int, num_classes: int, context: occplug.RunContext) -> None:
        super().__init__(in_channels, num_classes=num_classes)
        SEEN.append(context)


class DictGridHead(VoxelClassifier):
    """A third-party head that takes ``grid:`` from its config node as a mapping and parses nothing."""

    def __init__(self, in_channels: int, num_classes: int, grid: dict | GridSpec | None = None) -> None:
        super().__init__(in_channels, num_classes=num_classes)
        self.grid_arg = grid


class SpecGridHead(VoxelClassifier):
    def __init__(self, in_channels: int, num_classes: int, grid: GridSpec) -> None:
        super().__init__(in_channels, num_classes=num_classes)
        self.grid_arg = grid


class NotAHead(nn.Module):
    def forward(self, x: Tensor) -> Tensor:
        return x


class ContextPlugin:
    @occplug.hookimpl
    def occplug_register_components(self, registry: occplug.Registry) -> None:
        registry.add("scene", "toy_context_scene", ContextScene)
        registry.add("head", "toy_context_head", ContextHead)
        registry.add("head", "toy_dict_grid", DictGridHead)
        registry.add("head", "toy_spec_grid", SpecGridHead)


def test_the_run_context_is_immutable_and_holds_a_gridspec():
    context = occplug.RunContext(GRID, OCC3D_CLASSES, free_label=17, ignore_label=255, class_groups={"dynamic": [4]})
    assert context.num_classes == 18 and context.ids("dynamic") == (4,)
    with pytest.raises(dataclasses.FrozenInstanceError):
        context.grid = GRID  # type: ignore[misc]
    with pytest.raises(TypeError, match="does not support item assignment"):
        context.class_groups["static"] = (1,)  # type: ignore[index]
    with pytest.raises(ValueError, match=r"class group 'static' is not defined for these classes \(groups: dynamic\)"):
        context.ids("static")
    with pytest.raises(TypeError, match="RunContext.grid must be a GridSpec, got dict"):
        occplug.RunContext(GRID.to_dict(), (), free_label=0)  # type: ignore[arg-type]


def test_the_runner_builds_one_context_and_every_component_that_asks_gets_it(isolated_registry):
    isolated_registry(plugins=[("toy_context", ContextPlugin())])
    SEEN.clear()
    cfg = runner.load_config([BASELINE, *SMALL], ["model.scene={type: toy_context_scene}"])
    dm, model = runner.build_run(cfg)
    context = model.context
    assert [c is context for c in SEEN] == [True, True]  # the scene and the head it built, one object
    assert context.grid == GridSpec.from_config(cfg["grid"]) == model.grid and isinstance(context.grid, GridSpec)
    assert context.class_names == tuple(dm.class_names) == OCC3D_CLASSES and context.free_label == dm.free_label
    assert model.scene.dynamic == tuple(OCC3D_CLASSES.index(n) for n in OCC3D_DYNAMIC)
    assert context.eval_mask == "camera"


def test_a_config_cannot_set_the_context(isolated_registry):
    isolated_registry(plugins=[("toy_context", ContextPlugin())])
    with pytest.raises(occplug.config.ConfigError, match=r"model\.scene\.context"):
        runner.load_config([BASELINE, *SMALL], ["model.scene={type: toy_context_scene, context: 1}"])


def test_the_builder_parses_a_grid_for_a_gridspec_argument_and_leaves_a_mapping_argument_as_written(
    isolated_registry,
):
    registry = isolated_registry(plugins=[("toy_context", ContextPlugin())])
    node = {"range": [-2.0, -2.0, 0.0, 2.0, 2.0, 1.0], "voxel_size": 0.5}
    spec = registry.build("head", {"type": "toy_spec_grid", "grid": node}, in_channels=4, num_classes=3)
    assert spec.grid_arg == GRID and isinstance(spec.grid_arg, GridSpec)
    third_party = registry.build("head", {"type": "toy_dict_grid", "grid": node}, in_channels=4, num_classes=3)
    assert third_party.grid_arg == node  # a `grid:` the component takes from config still builds
    given = registry.build("head", {"type": "toy_spec_grid"}, in_channels=4, num_classes=3, grid=node)
    assert given.grid_arg == GRID


def test_the_builder_checks_arguments_the_given_ones_and_the_interface():
    registry = Registry()
    registry.add("head", "voxel_classifier", VoxelClassifier)
    with pytest.raises(
        ComponentArgumentError, match=r"unknown argument of head 'voxel_classifier'; did you mean 'hidden'"
    ) as info:
        registry.build("head", {"type": "voxel_classifier", "hiden": 4}, in_channels=4, num_classes=3)
    assert info.value.key == "hiden"
    with pytest.raises(ComponentArgumentError, match=r"expects its parent to give 'num_classes'"):
        registry.build("head", "voxel_classifier", in_channels=4)
    head = registry.build("head", "voxel_classifier", in_channels=4, num_classes=3, image_channels=7)
    assert head.num_classes == 3  # a given argument the factory does not take is not passed
    registry.add("head", "not_a_head", lambda: NotAHead())
    with pytest.raises(TypeError, match=r"head 'not_a_head' \(plugin occplug\) built a NotAHead, not a Head"):
        registry.build("head", "not_a_head")
    assert issubclass(VoxelClassifier, Head) and not issubclass(DenseVoxels, Head)
    assert issubclass(DenseVoxels, SceneRepresentation)


def test_a_nested_node_needs_the_context_outside_a_run():
    from occplug.components import LSSViewTransform

    lss = LSSViewTransform(in_channels=4, image_stride=4, grid=GRID, out_channels=3, depth_bins=[1.0, 5.0, 1.0])
    assert type(lss.depth_net).__name__ == "PlainDepthNet"  # no node: the plain depth net, no context needed
    with pytest.raises(ValueError, match="a depth_net node is built through the run context"):
        LSSViewTransform(in_channels=4, image_stride=4, grid=GRID, depth_net={"type": "camera_aware"})
    assert torch.is_tensor(lss.depth_centers)
