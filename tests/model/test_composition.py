"""Models beyond one chain: two encoders, multi-scale features, heads that read heads, extras.

The end-to-end test builds a model from registered parts only (a LiDAR branch, a two-level image
encoder, a head reading another head and the LiDAR volume, a supervision source reading an
``extras`` entry) and fits, validates and predicts it through the runner: no step, metric,
checkpoint or predict code outside the core.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import Tensor, nn

import occplug
from occplug.components import SmallCNN, VoxelPoints
from occplug.components.point_encoders import voxel_point_statistics
from occplug.config import validate
from occplug.geometry import GridSpec
from occplug.interfaces import ImageEncoder, ModelOutputs, OccupancyHead, Scene, SupervisionSource
from occplug.kinds import KINDS, given_arguments
from occplug.model import OccModel, head_order
from occplug.plugins import isolated
from occplug.run import runner
from occplug.testing import make_tiny_batch


class RefineHead(OccupancyHead):
    """Occupancy logits of the head it reads, plus a correction from the LiDAR volume."""

    def __init__(
        self,
        in_channels: int,
        num_classes: int = 18,
        reads: list[str] = ("occupancy",),
        lidar: str = "lidar",
        lidar_channels: int = 8,
    ) -> None:
        super().__init__()
        self.reads = tuple(reads)
        self.num_classes, self.lidar = num_classes, lidar
        self.delta = nn.Conv3d(lidar_channels, num_classes, 1)
        self.seen_levels: list[tuple[int, ...]] = []

    def forward(self, scene: Scene, batch, outputs: ModelOutputs) -> dict[str, Tensor]:
        base = outputs.heads[self.reads[0]]["logits"]
        delta = self.delta(outputs.encoded[self.lidar])
        self.seen_levels = [tuple(level.shape) for level in outputs.image_levels]
        outputs.extras["refine/delta"] = delta
        return {"logits": base + delta}

    def occupancy_logits(self, scene: Scene, grid: GridSpec) -> Tensor:  # evaluation reuses forward's logits
        raise TypeError("refine reads another head: evaluate through forward")

    @classmethod
    def conformance_inputs(cls, batch, grid, channels):
        scene, batch = OccupancyHead.conformance_inputs(batch, grid, channels)
        gen = torch.Generator().manual_seed(1)
        outputs = ModelOutputs(image_features=None, lifted=None, scene=scene, query=None,
                               heads={"occupancy": {"logits": torch.randn(len(batch), 18, *grid.shape, generator=gen)}},
                               encoded={"lidar": torch.randn(len(batch), 8, *grid.shape, generator=gen)})
        return scene, batch, outputs


class DeltaPenalty(SupervisionSource):
    """Reads a model-level extra: an L2 penalty on the refine head's correction."""

    def __init__(self, weight: float = 0.01, free_label: int = 17, ignore_label: int | None = 255) -> None:
        super().__init__()
        self.weight = weight

    def forward(self, batch, outputs: ModelOutputs) -> dict[str, Tensor]:
        return {"l2": outputs.extras["refine/delta"].square().mean()}

    @classmethod
    def conformance_outputs(cls, batch, grid, channels):
        delta = torch.randn(len(batch), 18, *grid.shape, requires_grad=True)
        return ModelOutputs(image_features=None, lifted=None, scene=None, heads={}, query=None,
                            extras={"refine/delta": delta})


class ComposedPlugin:
    @occplug.hookimpl
    def occplug_register_components(self, registry: occplug.Registry) -> None:
        registry.add("head", "toy_refine", RefineHead)
        registry.add("supervision", "toy_delta_penalty", DeltaPenalty)


# ------------------------------------------------------------------ head order


class _Stub(nn.Module):
    def __init__(self, reads=()):
        super().__init__()
        self.reads = tuple(reads)


def test_head_order_puts_each_head_after_what_it_reads():
    heads = {"decoder": _Stub(["agg"]), "agg": _Stub(["det"]), "det": _Stub(), "aux": _Stub()}
    assert head_order(heads) == ["det", "agg", "decoder", "aux"]  # earliest ready head in config order next
    assert head_order({"a": _Stub(), "b": _Stub()}) == ["a", "b"]  # config order kept


def test_head_order_rejects_unknown_names_and_cycles():
    with pytest.raises(ValueError, match=r"^model\.heads\.agg\.reads: no head named 'dett'; heads are: agg, det$"):
        head_order({"agg": _Stub(["dett"]), "det": _Stub()})
    with pytest.raises(ValueError, match="read each other in a cycle"):
        head_order({"a": _Stub(["b"]), "b": _Stub(["a"])})
    with pytest.raises(ValueError, match="cannot read its own outputs"):
        head_order({"a": _Stub(["a"])})


# ------------------------------------------------------------------ multi-scale encoder


def test_small_cnn_levels_share_the_primary_level_bit_for_bit():
    images = torch.rand(1, 2, 3, 32, 64)
    torch.manual_seed(0)
    one = SmallCNN(out_channels=8, width=8, stride=4).eval()
    torch.manual_seed(0)
    three = SmallCNN(out_channels=8, width=8, stride=4, levels=3).eval()
    levels = three(images)
    assert three.level_strides == (4, 8, 16) and three.level_channels == (8, 8, 8) and three.primary_level == 0
    assert [tuple(x.shape) for x in levels] == [(1, 2, 8, 8, 16), (1, 2, 8, 4, 8), (1, 2, 8, 2, 4)]
    assert torch.equal(levels[0], one(images))
    assert one.level_strides == (4,) and isinstance(one(images), Tensor)


@pytest.mark.parametrize(("stride", "num_blocks"), [(4, 2), (8, 2), (16, 1)])
def test_small_cnn_finer_level_adds_the_half_stride_features_and_keeps_the_primary(stride, num_blocks):
    """``finer_level``: level 0 is the stage before the last through its own neck, at ``stride / 2``; the primary
    level (now index 1) and the coarser ones equal the encoder without it, given the same weights."""
    images = torch.rand(1, 2, 3, 32, 64)
    plain = SmallCNN(out_channels=8, width=8, stride=stride, num_blocks=num_blocks, levels=2).eval()
    fine = SmallCNN(out_channels=8, width=8, stride=stride, num_blocks=num_blocks, levels=2, finer_level=True).eval()
    missing, unexpected = fine.load_state_dict(plain.state_dict(), strict=False)
    assert sorted(missing) == ["finer_neck.bias", "finer_neck.weight"] and not unexpected
    levels = fine(images)
    assert fine.primary_level == 1 and fine.level_strides == (stride // 2, stride, 2 * stride)
    assert fine.level_channels == (8, 8, 8) and (fine.out_channels, fine.stride) == (8, stride)
    assert [tuple(x.shape[-2:]) for x in levels] == [
        (64 // stride, 128 // stride),
        (32 // stride, 64 // stride),
        (16 // stride, 32 // stride),
    ]
    for a, b in zip(levels[1:], plain(images), strict=True):
        assert torch.equal(a, b)
    # the finer level by hand: everything before the last stage (the stem alone at stride 4), then its neck
    last_stage = num_blocks  # layers
    before = plain.body[: len(plain.body) - last_stage](plain.standardise(images.flatten(0, 1)))
    torch.testing.assert_close(levels[0].flatten(0, 1), fine.finer_neck(before), rtol=0, atol=0)
    assert before.shape[-2:] == (64 // stride, 128 // stride)


def test_small_cnn_finer_level_passes_the_encoder_contract():
    enc = SmallCNN(out_channels=8, width=8, stride=8, finer_level=True)
    grid = GridSpec.from_config({"range": [0, 0, 0, 2, 2, 1], "voxel_size": 1.0})
    ImageEncoder.check_conformance(enc, make_tiny_batch(), grid)


def test_small_cnn_rejects_images_the_coarsest_level_does_not_divide():
    with pytest.raises(ValueError, match="not divisible by the encoder stride 16"):
        SmallCNN(out_channels=4, width=4, stride=4, levels=3)(torch.rand(1, 1, 3, 24, 24))


# ------------------------------------------------------------------ point encoder


def test_voxel_point_statistics_known_values():
    grid = GridSpec.from_config({"range": [0, 0, 0, 2, 2, 1], "voxel_size": 1.0})
    pts = torch.tensor([[0.25, 0.5, 0.5], [0.75, 0.5, 0.5], [1.5, 1.5, 0.9], [5.0, 0.0, 0.0]])
    out = voxel_point_statistics(pts, torch.tensor([0.2, 0.4, 1.0, 0.7]), grid)
    assert out.shape == (5, 2, 2, 1)
    torch.testing.assert_close(
        out[:, 0, 0, 0], torch.tensor([np.log(3.0), 0.0, 0.0, 0.0, 0.3], dtype=torch.float32), rtol=0, atol=1e-6
    )
    torch.testing.assert_close(
        out[:, 1, 1, 0], torch.tensor([np.log(2.0), 0.0, 0.0, 0.4, 1.0], dtype=torch.float32), rtol=0, atol=1e-6
    )
    assert out[:, 0, 1].abs().sum() == 0 and out[:, 1, 0].abs().sum() == 0  # empty voxels; the far point dropped
    # non-finite rows (an exported graph's point padding) are no points: the same statistics
    nan = torch.full((2, 3), float("nan"))
    padded = voxel_point_statistics(torch.cat([pts, nan]), torch.tensor([0.2, 0.4, 1.0, 0.7, 0.5, float("nan")]), grid)
    torch.testing.assert_close(padded, out, rtol=0, atol=0)


def test_voxel_points_declares_points_and_runs_on_a_tiny_batch():
    batch = make_tiny_batch()
    grid = GridSpec.from_config({"range": [-16, -16, -1, 16, 16, 3], "voxel_size": 2.0})
    enc = VoxelPoints(grid, out_channels=4)
    assert "points" in enc.requires
    assert enc(batch).shape == (len(batch), 4, *grid.shape)


# ------------------------------------------------------------------ contracts


def test_every_kind_names_an_interface_and_its_given_arguments():
    assert set(KINDS) >= {
        "encoder",
        "point_encoder",
        "view_transform",
        "scene",
        "head",
        "supervision",
        "model",
        "data",
        "metric",
        "callback",
    }
    for kind in KINDS.values():
        assert isinstance(kind.interface(), type)
    assert given_arguments("head") == {"in_channels", "num_classes", "free_label", "grid", "image_channels"}
    assert given_arguments("view_transform") == {"in_channels", "image_stride", "level_channels", "level_strides", "grid"}
    assert "grid" in given_arguments("model") and "metrics" in given_arguments("model")


def test_registration_checks_the_base_class():
    class NotAHead(nn.Module):
        """Not a head."""

    reg = occplug.Registry()
    with pytest.raises(ValueError, match=r"head 'bad'.*must subclass occplug\.interfaces\.head\.Head"):
        reg.add("head", "bad", NotAHead)
    reg.add("head", "fine", RefineHead)  # a proper head registers


class LevelTransform(occplug.ViewTransform):
    """A view transform that needs the encoder's levels: ``level_strides`` is given by the model."""

    def __init__(self, in_channels: int, image_stride: int, level_strides: list[int], grid: dict,
                 out_channels: int = 4) -> None:
        super().__init__()
        self.level_strides, self.out_channels = list(level_strides), out_channels
        self.grid = GridSpec.from_config(grid)

    def forward(self, features, batch):
        raise NotImplementedError


class TeacherHead(RefineHead):
    """A head that widens ``given`` with an argument no core model passes."""

    given = (*OccupancyHead.given, "teacher_grid")

    def __init__(self, in_channels: int, teacher_grid: dict, num_classes: int = 18) -> None:
        super().__init__(in_channels, num_classes)


class GivenPlugin:
    @occplug.hookimpl
    def occplug_register_components(self, registry):
        registry.add("view_transform", "toy_levels", LevelTransform)
        registry.add("head", "toy_teacher", TeacherHead)


def test_given_arguments_are_left_out_of_configs_and_passed_by_the_parent():
    with isolated(plugins=[("given", GivenPlugin())]) as reg:
        base = ["data.preset=tiny", "model.encoder.levels=2"]
        cfg = runner.load_config(["configs/baseline.yaml"], [*base, "model.view_transform.type=toy_levels"])
        validate(cfg, reg)  # level_strides is required but given
        model = runner.build_model(cfg, runner.build_datamodule(cfg))
        assert model.view_transform.level_strides == [8, 16]  # the baseline encoder: stride 8, two levels
        # a widened given that this model does not pass: validation accepts it, the build names it in one line
        cfg = runner.load_config(["configs/baseline.yaml"], [*base, "model.heads.extra={type: toy_teacher}"])
        validate(cfg, reg)
        with pytest.raises(ValueError, match=r"^head 'toy_teacher' \(plugin given\) expects its parent to give 'teacher_grid'"):
            runner.build_model(cfg, runner.build_datamodule(cfg))


# ------------------------------------------------------------------ end to end


def composed_overrides() -> list[str]:
    return [
        "data.preset=tiny",
        "model.encoder.levels=2",
        "model.point_encoders={lidar: {type: voxel_points, out_channels: 8}}",
        "model.heads.refined={type: toy_refine, reads: [occupancy], lidar_channels: 8}",
        "model.occupancy_head=refined",
        "model.supervision.voxel_labels.head=refined",
        "model.supervision.delta={type: toy_delta_penalty, weight: 0.01}",
        "trainer.max_steps=3",
        "trainer.limit_val_batches=2",
    ]


def test_heads_reading_heads_see_their_outputs_exactly():
    with isolated(plugins=[("composed", ComposedPlugin())]):
        cfg = runner.load_config(["configs/baseline.yaml", "occplug/trainer/debug"], composed_overrides())
        dm = runner.build_datamodule(cfg)
        model = runner.build_model(cfg, dm)
        assert model.head_order == ["occupancy", "refined"]
        with torch.no_grad():
            model.heads["refined"].delta.weight.zero_()
            model.heads["refined"].delta.bias.zero_()
        model.eval()
        batch = make_tiny_batch()
        out = model(batch)
        assert torch.equal(out.heads["refined"]["logits"], out.heads["occupancy"]["logits"])
        assert [lvl[3:] for lvl in model.heads["refined"].seen_levels] == [
            tuple(out.image_features.shape[3:]),
            tuple(s // 2 for s in out.image_features.shape[3:]),
        ]
        assert set(out.encoded) == {"lidar"} and "refine/delta" in out.extras
        assert "points" in model.required_fields()


def test_two_encoders_and_a_reading_head_fit_validate_and_predict(tmp_path):
    with isolated(plugins=[("composed", ComposedPlugin())]):
        cfg = runner.load_config(["configs/baseline.yaml", "occplug/trainer/debug"], composed_overrides())
        results = runner.fit(cfg, tmp_path / "run")
        assert 0.0 <= results["mIoU"] <= 100.0
        ckpt = tmp_path / "run" / "checkpoints" / "last.ckpt"
        again = runner.evaluate(runner.resolve_run_config([], [], ckpt), ckpt)
        assert again.results["mIoU"] == pytest.approx(results["mIoU"], abs=1e-6)
        n = runner.predict(runner.resolve_run_config([], [], ckpt), ckpt, tmp_path / "preds")
        assert n > 0
        pred = np.load(next((tmp_path / "preds").glob("*.npz")))["pred"]
        assert pred.shape == tuple(GridSpec.from_config(cfg["grid"]).shape)


# ------------------------------------------------------------------ conformance inputs a component supplies


class BevScene(occplug.SceneRepresentation):
    """A BEV scene: needs a (B, C, X, Y) lifted plane, so it supplies its own conformance inputs."""

    def __init__(self, in_channels: int, out_channels: int = 4) -> None:
        super().__init__()
        self.out_channels = out_channels
        self.proj = nn.Conv2d(in_channels, out_channels, 1)

    def forward(self, lifted, batch):
        if lifted.volume.dim() != 4:
            raise ValueError("bev scene needs a (B, C, X, Y) plane")
        plane = self.proj(lifted.volume)  # (B, C, X, Y) -> a volume repeated along z, so it samples like voxels
        z = lifted.grid.shape[2]
        from occplug.interfaces import DenseVoxelScene

        return DenseVoxelScene(plane[..., None].expand(-1, -1, -1, -1, z).contiguous(), lifted.grid)

    @classmethod
    def conformance_inputs(cls, batch, grid, channels):
        from occplug.interfaces import Lifted

        plane = torch.randn(len(batch), channels, *grid.shape[:2], generator=torch.Generator().manual_seed(0))
        return (Lifted(volume=plane, grid=grid), batch)


class BevScenePlugin:
    @occplug.hookimpl
    def occplug_register_components(self, registry):
        registry.add("scene", "toy_bev", BevScene)


def test_a_component_supplies_its_own_conformance_inputs(monkeypatch):
    from occplug.testing import check_component

    with isolated(plugins=[("bev", BevScenePlugin())]):
        check_component("scene", "toy_bev", batch=make_tiny_batch())  # passes with its own BEV inputs
        # with the interface's default (a dense volume) the same component fails: the inputs really came from it
        monkeypatch.setattr(BevScene, "conformance_inputs", classmethod(occplug.SceneRepresentation.conformance_inputs.__func__))
        with pytest.raises(ValueError, match="needs a"):
            check_component("scene", "toy_bev", batch=make_tiny_batch())


def test_parts_that_read_outputs_pass_the_conformance_check():
    from occplug.testing import check_component

    with isolated(plugins=[("composed", ComposedPlugin())]):
        check_component("head", "toy_refine", {"lidar_channels": 8}, batch=make_tiny_batch())
        check_component("supervision", "toy_delta_penalty", batch=make_tiny_batch())


# ------------------------------------------------------------------ a plugin's own model class


class DoubledLogitsModel(OccModel):
    """A plugin's model class (kind ``model``): the core model with a config argument of its own that scales
    the occupancy logits; it writes no training, evaluation, prediction or checkpoint code."""

    def __init__(self, *args, logit_scale: float = 2.0, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.logit_scale = logit_scale

    def forward(self, batch):
        out = super().forward(batch)
        out.heads[self.occupancy_head]["logits"] = out.heads[self.occupancy_head]["logits"] * self.logit_scale
        return out


class ModelPlugin:
    @occplug.hookimpl
    def occplug_register_components(self, registry: occplug.Registry) -> None:
        registry.add("model", "doubled_logits", DoubledLogitsModel)


def test_a_plugins_model_class_fits_validates_and_predicts_through_the_core(tmp_path):
    with isolated(plugins=[("models", ModelPlugin())]):
        overrides = ["model.type=doubled_logits", "model.logit_scale=3.0", "trainer.max_steps=2", "trainer.limit_val_batches=2"]
        cfg = runner.load_config(["configs/baseline.yaml", "occplug/trainer/debug"], overrides)
        results = runner.fit(cfg, tmp_path / "run")
        ckpt = tmp_path / "run" / "checkpoints" / "last.ckpt"
        restored = runner.resolve_run_config([], [], ckpt)
        assert restored["model"]["type"] == "doubled_logits" and restored["model"]["logit_scale"] == 3.0
        again = runner.evaluate(restored, ckpt)
        assert again.results["mIoU"] == pytest.approx(results["mIoU"], abs=1e-6)
        assert runner.predict(restored, ckpt, tmp_path / "preds") > 0
        dm, model = runner.build_run(restored)
        assert type(model) is DoubledLogitsModel and model.logit_scale == 3.0
