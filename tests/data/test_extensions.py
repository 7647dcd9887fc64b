"""Plugins extend every data module through registered label sources, frame transforms and field collate rules."""

import pytest
import torch

from occplug.data import Frame
from occplug.data.frame import FieldRule, collate_frames, field_rule
from occplug.data.synthetic import SyntheticDataModule


def _frame(i, **extras):
    f = Frame(
        images=torch.zeros(1, 3, 4, 4),
        intrinsics=torch.eye(3)[None],
        cam_to_ego=torch.eye(4)[None],
        img_aug=torch.eye(3)[None],
        ego_to_global=torch.eye(4, dtype=torch.float64),
        timestamp=0.0,
        scene="s",
        frame_index=i,
        token=f"t{i}",
    )
    f.extras.update(extras)
    return f


def test_collate_rules_stack_pad_and_list():
    frames = [
        _frame(0, a=torch.tensor([1.0, 2.0]), b=torch.tensor([[1, 1]]), c="x"),
        _frame(1, a=torch.tensor([3.0, 4.0]), b=torch.tensor([[2, 2], [3, 3], [4, 4]]), c="y"),
    ]
    batch = collate_frames(frames, {"a": FieldRule("stack"), "b": FieldRule("pad", -7)})
    assert torch.equal(batch.extras["a"], torch.tensor([[1.0, 2.0], [3.0, 4.0]]))
    assert torch.equal(batch.extras["b"], torch.tensor([[[1, 1], [-7, -7], [-7, -7]], [[2, 2], [3, 3], [4, 4]]]))
    assert torch.equal(batch.extras["b_mask"], torch.tensor([[True, False, False], [True, True, True]]))
    assert batch.extras["c"] == ["x", "y"]
    # without rules every extra is a list, as before
    assert isinstance(collate_frames(frames).extras["a"], list)
    # the rule follows adjacent frames too
    for f, other in zip(frames, (_frame(5, a=torch.tensor([9.0, 9.0])), _frame(6, a=torch.tensor([8.0, 8.0]))), strict=False):
        f.adjacent[-1] = other
    assert torch.equal(
        collate_frames(frames, {"a": FieldRule("stack")}).adjacent[-1].extras["a"][:, 0], torch.tensor([9.0, 8.0])
    )
    with pytest.raises(ValueError, match="'b' is collated by 'stack'"):
        collate_frames(frames, {"b": FieldRule("stack")})
    with pytest.raises(ValueError, match="missing in some frames"):
        collate_frames([_frame(0, a=torch.ones(2)), _frame(1)], {"a": FieldRule("stack")})
    assert field_rule({"collate": "pad", "pad_value": 3}) == FieldRule("pad", 3.0)
    with pytest.raises(ValueError, match="data.fields.x: unknown collate rule 'stak'"):
        field_rule("stak", "data.fields.x")


def test_plugin_label_source_transform_and_field_reach_the_synthetic_batches(toy_extensions, tmp_path):
    dm = SyntheticDataModule(
        preset="tiny",
        cache_dir=str(tmp_path),
        batch_size=3,
        adjacent_offsets=[-1],
        label_sources={"ids": {"type": "toy_ids", "offset": 10}, "off": None},
        transforms=[{"type": "toy_tag", "scale": 2.0, "splits": ["train"]}],
        fields={"toy_tag": "stack"},
        registry=toy_extensions,
    )
    assert dm.field_rules == {"toy_ids": FieldRule("pad", -1), "toy_tag": FieldRule("stack")}
    # train scenes hold frames 0, 1, 2: the label source made [10], [10, 11], [10, 11, 12], padded with -1
    frames = [dm.dataset("train")[i] for i in range(3)]
    batch = dm.collate(frames)
    assert torch.equal(batch.extras["toy_ids"], torch.tensor([[10, -1, -1], [10, 11, -1], [10, 11, 12]]))
    assert torch.equal(batch.extras["toy_ids_mask"], batch.extras["toy_ids"] >= 0)
    assert batch.extras["toy_num_classes"] == [18, 18, 18]  # the data module's class names were passed
    # the label source ran on the adjacent frames (frame 0's previous frame is itself, clamped)
    assert torch.equal(batch.adjacent[-1].extras["toy_ids"], torch.tensor([[10, -1], [10, -1], [10, 11]]))
    # the transform ran last, after the pipeline, on the train split only
    assert torch.equal(batch.extras["toy_tag"], torch.tensor([[0.0, 1.0], [2.0, 1.0], [4.0, 1.0]]))
    assert batch.images.abs().sum() == 0
    loader_batch = next(iter(dm.val_dataloader()))
    assert "toy_tag" not in loader_batch.extras and loader_batch.images.abs().sum() > 0
    assert loader_batch.extras["toy_ids"].shape[0] == loader_batch.batch_size


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (
            {"transforms": [{"type": "toy_tga"}]},
            r"data.transforms\[0\].type: no transform 'toy_tga'; did you mean 'toy_tag'",
        ),
        (
            {"transforms": [{"type": "toy_tag", "scael": 1}]},
            r"data.transforms\[0\].scael: unknown argument of transform 'toy_tag'",
        ),
        (
            {"transforms": [{"type": "toy_tag", "splits": ["trian"]}]},
            r"data.transforms\[0\].splits: unknown split 'trian'",
        ),
        ({"transforms": {"type": "toy_tag"}}, r"data.transforms: expected a list"),
        ({"label_sources": {"ids": {"offset": 1}}}, r"data.label_sources.ids: expected a mapping with a 'type:'"),
        ({"label_sources": {"ids": {"type": "toy_tag"}}}, r"data.label_sources.ids.type: no label_source 'toy_tag'"),
        ({"fields": {"f": "pack"}}, r"data.fields.f: unknown collate rule 'pack'"),
    ],
)
def test_extension_config_errors_are_one_line_naming_the_key(toy_extensions, tmp_path, kwargs, message):
    with pytest.raises(ValueError, match=message) as info:
        SyntheticDataModule(preset="tiny", cache_dir=str(tmp_path), registry=toy_extensions, **kwargs)
    assert "\n" not in str(info.value)


def test_every_core_data_module_takes_the_extension_arguments():
    import inspect

    from occplug.plugins import get_registry

    for name in ("synthetic", "occ3d_nuscenes", "semantickitti"):
        params = inspect.signature(get_registry().get("data", name).factory).parameters
        assert {"label_sources", "transforms", "fields"} <= set(params), name


def test_a_config_names_them_by_registered_type(toy_extensions, tmp_path):
    import yaml

    from occplug.config.validate import validate

    cfg = yaml.safe_load(f"""
data:
  type: synthetic
  preset: tiny
  cache_dir: {tmp_path}
  label_sources: {{ids: {{type: toy_ids}}}}
  transforms: [{{type: toy_tag, scale: 3.0, splits: [val]}}]
  fields: {{toy_tag: stack}}
model: {{type: occ_model, encoder: {{type: small_cnn}},
        view_transform: {{type: lss, grid: {{range: [-16, -16, -1, 16, 16, 5.4], voxel_size: 0.8}}}}, scene: {{type: dense_voxels}},
        heads: {{occupancy: {{type: voxel_classifier}}}}, supervision: {{voxel_labels: {{type: voxel_ce}}}}}}
""")
    validate(cfg, toy_extensions)
    dm = toy_extensions.build("data", cfg["data"])
    batch = dm.collate([dm.dataset("val")[1]])
    assert torch.equal(batch.extras["toy_tag"], torch.tensor([[3.0, 0.0]]))
    assert torch.equal(batch.extras["toy_ids"], torch.tensor([[0, 1]]))
