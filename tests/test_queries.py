"""Queries in space and time: QueryResult, the chunked voxel default, and impossible query mixes."""

from __future__ import annotations

import dataclasses
import math
import weakref
from pathlib import Path

import pytest
import torch
from torch import Tensor, nn
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten

import occplug
from occplug.cli import main
from occplug.components import DenseVoxelScene, VoxelClassifier
from occplug.config import ConfigError, compose, validate
from occplug.geometry import GridSpec
from occplug.interfaces import OccupancyHead, QueryResult, Scene
from occplug.queries import check_query_support
from occplug.testing import check_component, make_tiny_batch

ROOT = Path(__file__).resolve().parents[1]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
TINY = ["data.preset=tiny", "trainer.accelerator=cpu", "trainer.enable_progress_bar=false"]
GRID = GridSpec(range=(-2.0, -1.6, -0.4, 2.0, 1.6, 1.2), voxel_size=0.4)  # (10, 8, 4): 320 centres
OCC3D = GridSpec(range=(-40.0, -40.0, -1.0, 40.0, 40.0, 5.4), voxel_size=0.4)  # (200, 200, 16): 640k centres


# ---------------------------------------------------------------- toy components
class OccupancyLogitHead(OccupancyHead):
    """Queryable head with a separate occupancy logit: class logits = the scene's first K channels,
    occupancy logit = channel K, features = the remaining channels."""

    queryable = True

    def __init__(self, in_channels: int, num_classes: int = 4, free_label: int = 3) -> None:
        super().__init__()
        self.num_classes, self.free_label = num_classes, free_label
        self.scale = nn.Parameter(torch.ones(()))
        self.offset = 0.0  # subtracted from the occupancy logit

    def forward(self, scene: Scene, batch: occplug.Batch) -> dict[str, Tensor]:
        return {"logits": self.occupancy_logits(scene, scene.grid)}

    def query(self, scene: Scene, points: Tensor, times: Tensor | None = None) -> QueryResult:
        self.check_query(points, times)
        f = scene.sample(points) * self.scale
        k = self.num_classes
        return QueryResult(class_logits=f[..., :k], occupancy_logit=f[..., k] - self.offset, features=f[..., k + 1 :])


class FixedHead(OccupancyHead):
    """An occupancy head that cannot be queried (its own voxel logits only)."""

    def __init__(self, in_channels: int, num_classes: int = 18) -> None:
        super().__init__()
        self.num_classes = num_classes
        self.bias = nn.Parameter(torch.zeros(num_classes))

    def forward(self, scene: Scene, batch: occplug.Batch) -> dict[str, Tensor]:
        return {"logits": self.occupancy_logits(scene, scene.grid)}

    def occupancy_logits(self, scene: Scene, grid: GridSpec, chunk_size: int = 1) -> Tensor:
        return self.bias.view(1, -1, 1, 1, 1).expand(scene.batch_size, -1, *grid.shape)


class ToyQuerySupervision(occplug.SupervisionSource):
    """Queries ``query_head`` at the tiny grid's centres at each of ``times``; its need for temporal
    queries depends on its arguments, so only the model build can see it."""

    def __init__(self, query_head: str = "occupancy", times: list[float] | None = None, weight: float = 1.0) -> None:
        super().__init__()
        self.query_head, self.weight = query_head, weight
        self.times = list(times or [0.0])
        self.needs_temporal_queries = any(t != 0 for t in self.times)

    def forward(self, batch: occplug.Batch, outputs: occplug.ModelOutputs) -> dict[str, Tensor]:
        grid = outputs.scene.grid
        pts = grid.centers()[::2, ::2, ::2].reshape(1, -1, 3).expand(len(batch), -1, -1)
        losses = {}
        for t in self.times:
            result = outputs.query(self.query_head, pts, torch.full(pts.shape[:2], t))
            losses[f"t{t:g}"] = result.class_logits.square().mean()
        return losses


class ToyTemporalSupervision(ToyQuerySupervision):
    """Always queries other time steps (declared on the class: config validation sees it)."""

    needs_temporal_queries = True

    def __init__(self, query_head: str = "occupancy", weight: float = 1.0) -> None:
        super().__init__(query_head, [0.0, 0.5], weight)


class ToyQueryPlugin:
    @occplug.hookimpl
    def occplug_register_components(self, registry: occplug.Registry) -> None:
        registry.add("supervision", "toy_query", ToyQuerySupervision)
        registry.add("supervision", "toy_temporal_query", ToyTemporalSupervision)
        registry.add("head", "toy_fixed", FixedHead)
        registry.add("head", "toy_occupancy_logit", OccupancyLogitHead)


class LivePeak(TorchDispatchMode):
    """Peak bytes of the CPU tensors created inside the mode that are alive at once (views share storage)."""

    def __init__(self) -> None:
        super().__init__()
        self.refs: dict[int, int] = {}
        self.size: dict[int, int] = {}
        self.current = self.peak = 0

    def _drop(self, key: int) -> None:
        self.refs[key] -= 1
        if self.refs[key] == 0:
            self.current -= self.size.pop(key)
            del self.refs[key]

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # type: ignore[no-untyped-def]
        out = func(*args, **(kwargs or {}))
        for t in tree_flatten(out)[0]:
            if isinstance(t, Tensor) and t.device.type == "cpu":
                storage = t.untyped_storage()
                key = storage.data_ptr()
                if key not in self.refs:
                    self.refs[key], self.size[key] = 0, storage.nbytes()
                    self.current += storage.nbytes()
                    self.peak = max(self.peak, self.current)
                self.refs[key] += 1
                weakref.finalize(t, self._drop, key)
        return out


def _centres(grid: GridSpec, b: int) -> Tensor:
    return grid.centers().reshape(1, -1, 3).expand(b, -1, -1)


def _reference(head: OccupancyHead, scene: Scene, grid: GridSpec) -> Tensor:
    """Unchunked: every centre in one query."""
    b = scene.batch_size
    return head.query(scene, _centres(grid, b)).logits(head.free_label).transpose(1, 2).reshape(b, -1, *grid.shape)


# ---------------------------------------------------------------- QueryResult
def test_query_result_shapes_are_checked() -> None:
    r = QueryResult(torch.zeros(2, 5, 4), torch.zeros(2, 5), torch.zeros(2, 5, 7))
    assert r.class_logits.shape == (2, 5, 4) and r.occupancy_logit.shape == (2, 5) and r.features.shape == (2, 5, 7)
    assert QueryResult(torch.zeros(2, 5, 4)).occupancy_logit is None
    with pytest.raises(ValueError, match=r"class_logits must be \(B, P, K\)"):
        QueryResult(torch.zeros(5, 4))
    with pytest.raises(ValueError, match=r"occupancy_logit must be \(B, P\) = \(2, 5\), got \(2, 5, 1\)"):
        QueryResult(torch.zeros(2, 5, 4), torch.zeros(2, 5, 1))
    with pytest.raises(ValueError, match=r"features must be \(B, P, F\)"):
        QueryResult(torch.zeros(2, 5, 4), None, torch.zeros(2, 4, 7))


def test_query_result_logits_combine_occupancy_known_values() -> None:
    cls = torch.tensor([[[1.0, 3.0, 2.0, 9.0], [1.0, 3.0, 2.0, -9.0], [0.5, -1.0, 0.0, 0.0]]])  # free = 3
    occ = torch.tensor([[2.0, -0.5, 0.25]])
    plain = QueryResult(cls)
    assert plain.logits() is cls  # no occupancy logit: the class logits themselves
    out = QueryResult(cls, occ).logits(free_label=3)
    # free's column = best occupied logit - occupancy logit; the other columns unchanged
    expected = cls.clone()
    expected[0, :, 3] = torch.tensor([3.0 - 2.0, 3.0 + 0.5, 0.5 - 0.25])
    assert torch.equal(out, expected)
    assert out.argmax(-1).tolist() == [[1, 3, 0]]  # occupied -> best non-free class; o < 0 -> free
    with pytest.raises(ValueError, match="needs free_label"):
        QueryResult(cls, occ).logits()
    with pytest.raises(ValueError, match="needs free_label"):
        QueryResult(cls, occ).logits(free_label=4)


# ---------------------------------------------------------------- the chunked default
@pytest.mark.parametrize("chunk", [7, 64, 320, 10_000])
def test_chunked_occupancy_logits_equal_unchunked_reference(chunk: int) -> None:
    """Exactly equal for a head whose answer at a point depends on that point only (trilinear reads of a
    coarser scene, between its centres); an MLP head agrees to float rounding (BLAS blocks by chunk length)."""
    torch.manual_seed(0)
    coarse = GridSpec(range=(-2.0, -1.6, -0.4, 2.0, 1.6, 1.2), voxel_size=0.8)
    scene = DenseVoxelScene(torch.randn(2, 9, *coarse.shape), coarse)
    sampler = OccupancyLogitHead(in_channels=9, num_classes=4, free_label=3)
    mlp = VoxelClassifier(in_channels=9, num_classes=5, hidden=16)
    with torch.no_grad():
        out = sampler.occupancy_logits(scene, GRID, chunk_size=chunk)
        assert out.shape == (2, 4, *GRID.shape)
        torch.testing.assert_close(out, _reference(sampler, scene, GRID), rtol=0, atol=0)
        out = OccupancyHead.occupancy_logits(mlp, scene, GRID, chunk_size=chunk)  # the base default
        assert out.shape == (2, 5, *GRID.shape)
        torch.testing.assert_close(out, _reference(mlp, scene, GRID), rtol=1e-6, atol=1e-6)


def test_chunked_default_with_an_occupancy_logit_head() -> None:
    torch.manual_seed(0)
    head = OccupancyLogitHead(in_channels=7, num_classes=4, free_label=1)
    scene = DenseVoxelScene(torch.randn(2, 7, *GRID.shape), GRID)
    out = head.occupancy_logits(scene, GRID, chunk_size=50)
    torch.testing.assert_close(out, _reference(head, scene, GRID), rtol=0, atol=0)
    # at voxel centres the scene reads exactly its features: known class ids from the two-stage rule
    f = scene.features
    cls, occ = f[:, :4], f[:, 4]
    best = cls.masked_fill(torch.tensor([False, True, False, False]).view(1, 4, 1, 1, 1), -math.inf).argmax(1)
    expected = torch.where(occ > 0, best, torch.ones_like(best))
    assert torch.equal(out.argmax(1), expected)
    out.sum().backward()  # the chunked default keeps the graph (heads may train through it)
    assert head.scale.grad is not None and head.scale.grad != 0
    head.free_label = None
    with pytest.raises(ValueError, match="needs free_label"):
        head.occupancy_logits(scene, GRID)


class SlabHead(OccupancyHead):
    """A queryable field occupied (class 0) below ``z = top`` and free above: a ground whose surface a voxel may only
    clip."""

    queryable = True

    def __init__(self, top: float) -> None:
        super().__init__()
        self.num_classes, self.free_label, self.top = 2, 1, top

    def forward(self, scene: Scene, batch: occplug.Batch) -> dict[str, Tensor]:
        return {"logits": self.occupancy_logits(scene, scene.grid)}

    def query(self, scene: Scene, points: Tensor, times: Tensor | None = None) -> QueryResult:
        self.check_query(points, times)
        occ = torch.where(points[..., 2] < self.top, 5.0, -5.0)
        classes = torch.stack([points[..., 0], torch.zeros_like(occ)], -1)  # class 0's logit: x, for the gather check
        return QueryResult(class_logits=classes, occupancy_logit=occ)


def test_voxel_samples_mark_a_voxel_the_surface_only_clips_and_one_sample_is_the_centre() -> None:
    grid = GridSpec(range=(0.0, 0.0, 0.0, 0.8, 0.4, 0.8), voxel_size=0.4)  # (2, 1, 2); z voxels [0, .4), [.4, .8)
    head = SlabHead(top=0.15)  # below the first voxel's centre (z = 0.2): the centre is free
    scene = DenseVoxelScene(torch.zeros(1, 1, *grid.shape), grid)
    centre = head.occupancy_logits(scene, grid).argmax(1)[0]
    assert centre.tolist() == [[[1, 1]], [[1, 1]]]  # every voxel free at its centre
    head.voxel_samples = 2  # sub-cell centres at z = 0.1 and 0.3 in the first layer: 0.1 lies in the slab
    sub = head.occupancy_logits(scene, grid, chunk_size=3)
    assert sub.argmax(1)[0].tolist() == [[[0, 1]], [[0, 1]]]
    # the occupied voxel takes its most occupied sub-cell's answer: class 0's logit x at a sub-cell centre
    assert float(sub[0, 0, 0, 0, 0]) in (pytest.approx(0.1), pytest.approx(0.3))
    head.voxel_samples = 1
    head.top = 0.25  # above the centre: one sample finds it
    assert head.occupancy_logits(scene, grid).argmax(1)[0].tolist() == [[[0, 1]], [[0, 1]]]


def test_occ3d_size_default_is_chunked_with_bounded_memory() -> None:
    """640k centres: one query per chunk, each at most chunk_size points, memory beyond the output bounded by
    the chunk (measured: every tensor made during the call), and equal to the dense fast path."""
    torch.manual_seed(0)
    c, hidden, k, chunk = 8, 16, 18, 32768
    head = VoxelClassifier(in_channels=c, num_classes=k, hidden=hidden).eval()
    scene = DenseVoxelScene(torch.randn(1, c, *OCC3D.shape), OCC3D)
    calls: list[int] = []
    query = head.query

    def spy(scene: Scene, points: Tensor, times: Tensor | None = None) -> QueryResult:
        calls.append(points.shape[1])
        return query(scene, points, times)

    head.query = spy  # type: ignore[method-assign]
    with torch.no_grad():
        with LivePeak() as mem:
            out = OccupancyHead.occupancy_logits(head, scene, OCC3D, chunk_size=chunk)
        fast = head.occupancy_logits(scene, OCC3D)  # the dense path on the scene's own grid
    n = 200 * 200 * 16
    assert calls == [chunk] * (n // chunk) + [n % chunk] and len(calls) == math.ceil(n / chunk)
    output_bytes = out.numel() * 4
    extra = mem.peak - output_bytes
    # per query point: coordinates, indices, the sampled features, hidden and class logits (x2 for copies)
    bound = chunk * 2 * 8 * (3 + 3 + c + hidden + k)
    assert 0 < extra <= bound, f"{extra} bytes beyond the output, bound {bound}"
    assert bound < 0.25 * n * 4 * (c + hidden + k)  # far below the unchunked intermediates
    # float32 normalisation of centres on a 200-voxel axis gives trilinear weights ~1e-6 off one-hot
    torch.testing.assert_close(out, fast, atol=2e-4, rtol=0)


def test_a_head_that_is_not_queryable_must_implement_occupancy_logits() -> None:
    head = FixedHead(in_channels=4, num_classes=3)
    scene = DenseVoxelScene(torch.zeros(1, 4, *GRID.shape), GRID)
    with pytest.raises(TypeError, match="cannot be queried"):
        head.query(scene, _centres(GRID, 1))
    with pytest.raises(TypeError, match="FixedHead is not queryable: it must implement occupancy_logits"):
        OccupancyHead.occupancy_logits(head, scene, GRID)


def test_non_temporal_head_rejects_times_other_than_zero() -> None:
    head = VoxelClassifier(in_channels=4, num_classes=3, hidden=0)
    scene = DenseVoxelScene(torch.randn(2, 4, *GRID.shape), GRID)
    pts = _centres(GRID, 2)[:, :10]
    at_zero = head.query(scene, pts, torch.zeros(2, 10))
    assert torch.equal(at_zero.class_logits, head.query(scene, pts).class_logits)
    times = torch.zeros(2, 10)
    times[1, 3] = -0.5
    with pytest.raises(ValueError, match=r"VoxelClassifier is not temporal: .* got times in \[-0.5, 0\] s"):
        head.query(scene, pts, times)
    with pytest.raises(ValueError, match=r"times must be \(B, P\)"):
        head.query(scene, pts, torch.zeros(2, 9))
    with pytest.raises(ValueError, match=r"points must be \(B, P, 3\)"):
        head.query(scene, pts[..., :2])


# ---------------------------------------------------------------- impossible mixes
def test_check_query_support_names_both_keys() -> None:
    dense, fixed = VoxelClassifier(4, 3), FixedHead(4, 3)
    ok = ToyQuerySupervision("occupancy")
    check_query_support({"occupancy": dense}, {"q": ok, "plain": nn.Identity()})  # no error
    with pytest.raises(ConfigError) as err:
        check_query_support({"occupancy": fixed}, {"q": ok})
    assert str(err.value) == (
        "model.supervision.q (ToyQuerySupervision): queries model.heads.occupancy, "
        "but FixedHead cannot be queried at points (queryable = False)"
    )
    with pytest.raises(ConfigError) as err:
        check_query_support({"occupancy": dense}, {"q": ToyQuerySupervision("occupancy", [0.0, 0.5])})
    assert "model.supervision.q (ToyQuerySupervision): queries at times t != 0, but model.heads.occupancy" in str(
        err.value
    )
    assert "(VoxelClassifier) is not temporal" in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="queries head 'aux' but model.heads has no such head"):
        check_query_support({"occupancy": dense}, {"q": ToyQuerySupervision("aux")})
    temporal = type("TemporalHead", (VoxelClassifier,), {"temporal": True})(4, 3)
    check_query_support({"occupancy": temporal}, {"q": ToyTemporalSupervision()})


def test_query_supervision_trains_through_model_outputs(isolated_registry) -> None:
    """ModelOutputs.query(head, points, times) reaches the head; conformance builds the model around it."""
    isolated_registry(plugins=[("toyq", ToyQueryPlugin())])
    source = check_component("supervision", "toy_query", {"times": [0.0]}, batch=make_tiny_batch())
    assert source.query_head == "occupancy" and not source.needs_temporal_queries


def test_model_injects_free_label_into_heads(isolated_registry) -> None:
    isolated_registry(plugins=[("toyq", ToyQueryPlugin())])
    from occplug.context import RunContext
    from occplug.model import OccModel
    from occplug.plugins import get_registry

    grid = GRID.to_dict()
    model = OccModel(
        encoder={"type": "small_cnn", "out_channels": 8, "width": 8, "stride": 4},
        view_transform={"type": "lss", "grid": grid, "out_channels": 8, "hidden": 0, "depth_bins": [1.0, 5.0, 1.0]},
        scene={"type": "dense_voxels", "out_channels": 9, "num_blocks": 0},
        heads={"occupancy": {"type": "toy_occupancy_logit", "num_classes": 4}},
        supervision={},
        grid=grid,
        class_names=["a", "free", "b", "c"],
        free_label=1,
        context=RunContext(GRID, ("a", "free", "b", "c"), free_label=1, registry=get_registry()),
    )
    assert model.heads["occupancy"].free_label == 1
    model.eval()
    outputs = model(occplug.testing.hand_batch(1, image_hw=(16, 16)))
    f = torch.randn(1, 9, *GRID.shape, generator=torch.Generator().manual_seed(0))
    # known features (the hand batch sees nothing); no forward logits, so evaluation asks occupancy_logits
    outputs = dataclasses.replace(outputs, scene=DenseVoxelScene(f, GRID), heads={"occupancy": {}})
    pred = model.occupancy_from(outputs)
    logits = f[:, :4].clone()
    logits[:, 1] = -math.inf
    best, occ = logits.argmax(1), f[:, 4] - model.heads["occupancy"].offset
    expected = torch.where(occ > 0, best, torch.where(occ < 0, 1, best.clamp(max=1)))  # a tie: the lower label id
    assert torch.equal(pred, expected) and {1} < set(pred.unique().tolist())
    result = outputs.query("occupancy", _centres(GRID, 1)[:, :5], torch.zeros(1, 5))
    assert isinstance(result, QueryResult) and result.features.shape == (1, 5, 4)


def _cfg(*overrides: str) -> dict:
    return compose([BASELINE], [*TINY, *overrides]).resolved()


def test_config_validation_rejects_declared_impossible_mixes(isolated_registry) -> None:
    isolated_registry(plugins=[("toyq", ToyQueryPlugin())])
    validate(_cfg("model.supervision.q.type=toy_query"), occplug.plugins.get_registry())  # fine
    with pytest.raises(
        ConfigError,
        match=r"^model.supervision.q \(toy_temporal_query\): queries at times t != 0, "
        r"but model.heads.occupancy \(voxel_classifier\) is not temporal",  # both by their type:
    ):
        validate(_cfg("model.supervision.q.type=toy_temporal_query"), occplug.plugins.get_registry())
    with pytest.raises(
        ConfigError,
        match=r"model.supervision.q \(toy_query\): queries model.heads.occupancy, but toy_fixed cannot be queried",
    ):
        validate(
            _cfg("model.supervision.q.type=toy_query", "model.heads.occupancy.type=toy_fixed"),
            occplug.plugins.get_registry(),
        )
    with pytest.raises(ConfigError, match=r"queries head 'aux' but model.heads has no such head \(heads: occupancy\)"):
        validate(
            _cfg("model.supervision.q.type=toy_query", "model.supervision.q.query_head=aux"),
            occplug.plugins.get_registry(),
        )
    # an argument-dependent need passes validation: the model build catches it (next test)
    validate(
        _cfg("model.supervision.q.type=toy_query", "model.supervision.q.times=[0.0,0.5]"),
        occplug.plugins.get_registry(),
    )


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["model.supervision.q.type=toy_temporal_query"], "is not temporal"),  # config validation
        (["model.supervision.q.type=toy_query", "model.supervision.q.times=[0.0,0.5]"], "is not temporal"),  # build
        (["model.supervision.q.type=toy_query", "model.heads.occupancy.type=toy_fixed"], "cannot be queried"),
    ],
)
def test_fit_rejects_impossible_mix_in_one_line_writing_nothing(
    isolated_registry, tmp_path, capsys, overrides, message
):
    isolated_registry(plugins=[("toyq", ToyQueryPlugin())])
    run = tmp_path / "run"
    assert main(["fit", "-c", BASELINE, *TINY, *overrides, "--run-dir", str(run)]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: model.supervision.q (") and message in lines[0], captured.err
    assert "model.heads.occupancy" in lines[0] and "Traceback" not in captured.err
    assert not run.exists()


def test_config_validate_and_show_reject_impossible_mix(isolated_registry, capsys):
    isolated_registry(plugins=[("toyq", ToyQueryPlugin())])
    for action in ("validate", "show"):
        assert main(["config", action, "-c", BASELINE, "model.supervision.q.type=toy_temporal_query"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and err.startswith("error: model.supervision.q (toy_temporal_query)"), err
    assert main(["config", "validate", "-c", BASELINE, "model.supervision.q.type=toy_query"]) == 0
    assert capsys.readouterr().out.strip() == f"ok: {BASELINE}"
