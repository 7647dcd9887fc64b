"""``occplug export``: both formats on the tiny preset, the parity report, refusals with one line.

Adding a plugin's model is one line: a ``pytest.param`` in :data:`RECIPES` (its config refs and overrides).
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import importlib.util
import json
import shutil
import sys
from collections.abc import Iterator
from importlib import metadata
from pathlib import Path

import pytest
import torch

from occplug import export as ex
from occplug.cli import main
from occplug.export.tracing import _index_add_as_scatter_add, _inverse3
from occplug.plugins import ENTRY_POINT_GROUP, isolated
from occplug.run import runner
from occplug.testing import run_config

# one pytest-xdist worker runs the whole module (pyproject: --dist loadgroup): each recipe is fitted and exported
# once, and the tests after an export read its artefact (_EXPORTED)
pytestmark = pytest.mark.xdist_group("export")

ROOT = Path(__file__).resolve().parents[1]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
TINY = ["data.preset=tiny", "trainer.max_steps=2"]
STREAMING = ("data.sequential=true", "model.scene.type=dense_voxels_history")
#: A plugin by (entry point name, source folder, hook module): loaded from its source tree when not installed.
EXAMPLE = ("example", ROOT / "plugins" / "example" / "src", "occplug_example.plugin")

#: OccLE on 8 x 8 x 4 voxels, 2 Dual Mamba levels, scan chunks of 16: the traced graph stays small.
OCCLE_SMALL = ("grid.range=[0.0,-3.2,-1.0,6.4,3.2,2.2]", "model.scene.mamba_channels=[16,24]", "model.scene.mamba_chunk=16")

#: (config refs, overrides, plugin or None) of every model whose export is checked; one line per model.
RECIPES = [
    pytest.param(((BASELINE,), (), None), id="baseline"),
    pytest.param(((BASELINE,), STREAMING, None), id="streaming"),
    pytest.param((("example/tiny",), (), EXAMPLE), id="example"),
    # a method plugin shipped in this distribution (its entry point loads it): a BEV plane read by a query decoder
    pytest.param((("queryocc/base",), (), None), id="queryocc"),
    # DuOcc: the stateful StreamAgg scene (its history an explicit input and output), and the stacking baseline
    pytest.param((("duocc/stream_agg",), (), None), id="duocc_stream_agg"),
    pytest.param((("duocc/stacking",), (), None), id="duocc_stacking"),
    # DuOcc C: StreamAgg + the detector, whose propagated instances are stream state too
    pytest.param((("duocc/det_only",), (), None), id="duocc_det_only"),
    # DuOcc D: + V2Q and DQA (traced on its dense masked path: fixed shapes, no edge list); every query selected,
    # so DQA writes into voxels after 2 training steps too
    pytest.param((("duocc/full",), ("model.scene.query_agg.score_threshold=0.0",), None), id="duocc_full"),
    # OccLE: LiDAR points as a graph input (dynamic point count), the Hilbert-serialised Dual Mamba
    pytest.param((("occle/base",), OCCLE_SMALL, None), id="occle"),
]


@contextlib.contextmanager
def plugin_from_source(plugin: tuple[str, Path, str] | None) -> Iterator[None]:
    """The plugin registered through its hook module, as its entry point would (the installed one if there is).

    Not installed, its source folder goes on ``sys.path`` and its hook module is registered beside
    the installed plugins (:func:`occplug.plugins.isolated`) until the block ends; then no trace is left.
    """
    if plugin is None:
        yield
        return
    name, src, module = plugin
    package = module.split(".")[0]
    installed = sorted({ep.name for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)})
    if name in installed:  # installed: its entry point loads it (importable alone is not enough: another
        yield  # test may have left its source folder on sys.path)
        return
    sys.path.insert(0, str(src))
    try:
        with isolated(installed, [(name, importlib.import_module(module))]):
            yield
    finally:
        sys.path.remove(str(src))
        for loaded in [m for m in sys.modules if m == package or m.startswith(f"{package}.")]:
            del sys.modules[loaded]


_FITTED: dict[tuple, Path] = {}


def _fitted(recipe: tuple, factory) -> Path:
    """The checkpoint of ``recipe`` after a 2-step fit on the tiny preset (one fit per recipe and session)."""
    refs, overrides, _ = recipe
    key = (tuple(refs), tuple(overrides))
    if key not in _FITTED:
        run = factory.mktemp("export") / "run"
        run_config(*refs, run_dir=run, overrides=[*TINY, *overrides])
        _FITTED[key] = run / "checkpoints" / "last.ckpt"
    return _FITTED[key]


#: The artefact an export test wrote for (checkpoint, format) in this process. A test that needs the exported graph
#: of a checkpoint takes it from here rather than export it again: every export of a checkpoint has the same template
#: (its first validation frame, batch size 1: :func:`occplug.export.export_checkpoint` and :func:`_restored` alike).
_EXPORTED: dict[tuple[Path, str], Path] = {}


def _exported(ckpt: Path, fmt: str, factory) -> Path:
    """``ckpt`` exported to ``fmt`` (``torch_export`` or ``onnx``): the artefact of an earlier test, else a new one."""
    key = (ckpt, fmt)
    if key not in _EXPORTED:
        model, (batch,) = _restored(ckpt, frames=1)
        out = factory.mktemp("exported") / ("model.pt2" if fmt == "torch_export" else "model.onnx")
        ex.export_model(model, batch, fmt, out)
        _EXPORTED[key] = out
    return _EXPORTED[key]


@pytest.fixture(scope="module", params=RECIPES)
def checkpoint(request, tmp_path_factory) -> Iterator[Path]:
    with plugin_from_source(request.param[2]):
        yield _fitted(request.param, tmp_path_factory)


@pytest.fixture(scope="module")
def baseline_checkpoint(tmp_path_factory) -> Path:
    return _fitted(((BASELINE,), (), None), tmp_path_factory)


@pytest.fixture(scope="module")
def streaming_checkpoint(tmp_path_factory) -> Path:
    return _fitted(((BASELINE,), STREAMING, None), tmp_path_factory)


def _restored(ckpt: Path, frames: int = 2):
    cfg = runner.resolve_run_config([], [], ckpt)
    dm, model = runner.restore_run(cfg, runner.load_checkpoint(ckpt), ckpt)
    model.eval()
    data = dm.dataset("val")
    return model, [dm.collate([data[i]]) for i in range(frames)]


@pytest.mark.parametrize("fmt", ["torch_export", "onnx"])
def test_export_parity(checkpoint, fmt, tmp_path, capsys):
    if fmt == "onnx" and importlib.util.find_spec("onnxruntime") is None:
        pytest.skip("the export extra (onnx, onnxruntime, onnxscript) is not installed")
    out = tmp_path / ("model.pt2" if fmt == "torch_export" else "model.onnx")
    assert main(["export", "--ckpt", str(checkpoint), "--format", fmt, "--out", str(out), "--samples", "3"]) == 0
    printed = capsys.readouterr().out.strip().splitlines()
    assert len(printed) == 1 and printed[0].startswith(f"parity {fmt}: 3 frames + 3 perturbed")
    report = json.loads((tmp_path / f"{out.name}.parity.json").read_text())
    assert out.is_file() and sorted(p.name for p in tmp_path.iterdir()) == [out.name, f"{out.name}.parity.json"]
    assert report["frames"] == 3 and report["frames_perturbed"] == 3 and report["passed"] is True
    assert report["class_agreement"] >= 0.9999
    assert report["max_abs_logit_diff"] <= 1e-4
    assert report["eager_latency_ms"] > 0 and report["exported_latency_ms"] > 0
    assert report["versions"]["torch"] == torch.__version__
    _EXPORTED.setdefault((checkpoint, fmt), out)
    if fmt == "onnx":
        import onnxruntime

        assert report["versions"]["onnxruntime"] == onnxruntime.__version__
        _assert_deterministic_across_threads(checkpoint, out)


def _assert_deterministic_across_threads(checkpoint: Path, artefact: Path) -> None:
    """The splat's scatter-add runs in onnxruntime with several threads: the same bits every run."""
    import onnxruntime as ort

    model, (batch,) = _restored(checkpoint, frames=1)
    options = ort.SessionOptions()
    options.intra_op_num_threads = 4
    # idle threads sleep: a spinning pool of 4 would burn, between the runs, the cores the other tests run on
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    session = ort.InferenceSession(str(artefact), options, providers=["CPUExecutionProvider"])
    feed = {i.name: a.numpy() for i, a in zip(session.get_inputs(), ex.example_inputs(model, batch), strict=True)}
    first = session.run(None, feed)[1]
    assert all((session.run(None, feed)[1] == first).all() for _ in range(8))


def test_exported_graph_takes_the_calibration(checkpoint, tmp_path_factory):
    """Another rig through the same artefact: the output moves with the geometry and still matches eager."""
    model, (batch, _) = _restored(checkpoint)
    run = ex.load_exported(_exported(checkpoint, "torch_export", tmp_path_factory), "torch_export")
    other = ex.perturb(batch, seed=3)
    args = ex.example_inputs(model, batch)  # a streaming model: the first frame of a stream
    same = run(*args)[1]
    names = ex.graph_inputs(model)
    moved = run(*ex.inputs_of(other, names), *args[len(names) :])[1]
    with torch.no_grad():
        eager = ex.occupancy_logits(model, model(other))
    change, error = float((moved - same).abs().max()), float((moved - eager).abs().max())
    assert error <= 1e-4
    # the geometry is an input, not a constant: the rig moves the output far beyond the export's error
    assert change > max(100 * error, 1e-5)


@pytest.fixture(scope="module")
def occle_checkpoint(tmp_path_factory) -> Path:
    return _fitted((("occle/base",), OCCLE_SMALL, None), tmp_path_factory)


def test_lidar_graph_takes_any_point_count_and_ignores_nan_padding(occle_checkpoint, tmp_path_factory):
    """A model reading LiDAR: points (NaN-padded, the count dynamic) and lidar_to_ego are graph inputs."""
    model, (batch, other) = _restored(occle_checkpoint)
    names = ex.graph_inputs(model)
    assert names == (*ex.INPUTS, "points", "lidar_to_ego")
    run = ex.load_exported(_exported(occle_checkpoint, "torch_export", tmp_path_factory), "torch_export")
    # another frame's cloud (another count), then every other point of it, padded back with NaN rows
    count = int(other.points[0].shape[0])
    assert count != int(batch.points[0].shape[0])
    cut = dataclasses.replace(other, points=[other.points[0][::2]])
    with torch.no_grad():
        eager_other = ex.occupancy_logits(model, model(other))
        eager_cut = ex.occupancy_logits(model, model(cut))
    got_other = run(*ex.inputs_of(other, names))[1]
    args = list(ex.inputs_of(cut, names))
    args[names.index("points")] = ex.pad_points([cut.points[0], other.points[0]])[:1]  # padded to `count` rows
    assert args[names.index("points")].shape[1] == count and torch.isnan(args[names.index("points")]).any()
    got_cut = run(*args)[1]
    assert float((got_other - eager_other).abs().max()) <= 1e-4
    assert float((got_cut - eager_cut).abs().max()) <= 1e-4
    assert float((eager_cut - eager_other).abs().max()) > 1e-3  # the points are an input, not a constant
    # so is the LiDAR pose: another lidar_to_ego moves the output, eager and exported alike
    turned = dataclasses.replace(other, lidar_to_ego=ex.perturb(other, seed=5).lidar_to_ego)
    with torch.no_grad():
        eager_turned = ex.occupancy_logits(model, model(turned))
    assert float((run(*ex.inputs_of(turned, names))[1] - eager_turned).abs().max()) <= 1e-4
    assert float((eager_turned - eager_other).abs().max()) > 1e-3


def test_component_reading_a_field_that_is_no_graph_input_is_refused(baseline_checkpoint, monkeypatch):
    model, _ = _restored(baseline_checkpoint, frames=1)
    assert ex.graph_inputs(model) == ex.INPUTS  # reads no points: the camera inputs only
    monkeypatch.setattr(model.scene, "requires", frozenset({"boxes"}), raising=False)
    with pytest.raises(ex.ExportError, match=r"^model\.scene \(\w+\) reads batch field\(s\) boxes; the exported graph"):
        ex.check_exportable(model)
    monkeypatch.setattr(model.scene, "requires", frozenset({"points"}), raising=False)
    ex.check_exportable(model)  # LiDAR is a graph input
    assert ex.graph_inputs(model) == (*ex.INPUTS, *ex.POINT_INPUTS)


def test_pad_points_pads_with_nan_rows():
    a, b = torch.arange(8.0).view(2, 4), torch.ones(3, 4)
    padded = ex.pad_points([a, b])
    assert padded.shape == (2, 3, 4) and padded.dtype == torch.float32
    assert torch.equal(padded[0, :2], a) and torch.isnan(padded[0, 2]).all() and torch.equal(padded[1], b)
    single = ex.pad_points([torch.ones(1, 4)])  # at least 2 rows: the graph's point count starts at 2
    assert single.shape == (1, 2, 4) and torch.isnan(single[0, 1]).all()
    with pytest.raises(ValueError, match="no point cloud"):
        ex.pad_points([])


def test_cached_splat_plan_cannot_be_traced(checkpoint, monkeypatch):
    """Without export_ready the splat's plan cache (a host-side hash of the calibration) stops torch.export."""
    model, (batch,) = _restored(checkpoint, frames=1)
    if not hasattr(model, "view_transform") or not hasattr(model.view_transform, "splatter"):
        pytest.skip("no lift-splat view transform")
    monkeypatch.setattr("occplug.export.graph.export_ready", lambda model: contextlib.nullcontext())
    with pytest.raises(ex.ExportError) as err:
        ex.trace(model, batch)
    message = str(err.value)
    assert "\n" not in message
    name = type(model.view_transform).__name__
    assert message.startswith(f"export: model.view_transform ({name}) cannot be traced at splat.py:")
    assert "data-dependent control flow" in message


def test_untraceable_component_is_named(checkpoint, monkeypatch):
    model, (batch,) = _restored(checkpoint, frames=1)
    head = model.heads[model.occupancy_head]
    forward = head.forward

    def branchy(scene, batch):
        out = forward(scene, batch)
        if out["logits"].sum() > 0:  # data-dependent Python control flow
            return out
        return out

    monkeypatch.setattr(head, "forward", branchy)
    with pytest.raises(ex.ExportError) as err:
        ex.trace(model, batch)
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith(f"export: model.heads.occupancy ({type(head).__name__}) cannot be traced at test_export.py:")
    assert "`if out[\"logits\"].sum() > 0:" in message and "data-dependent control flow" in message


@pytest.mark.skipif(importlib.util.find_spec("onnxscript") is None, reason="the export extra is not installed")
def test_operation_without_onnx_translation_is_named(checkpoint, monkeypatch, tmp_path):
    model, (batch,) = _restored(checkpoint, frames=1)
    head = model.heads[model.occupancy_head]
    forward = head.forward

    def inverting(scene, batch):
        out = forward(scene, batch)
        pose = torch.linalg.inv(batch.cam_to_ego[:, :1].float())  # a 4x4 inverse: ONNX has none
        return {"logits": out["logits"] + pose[:, 0, 0, 0].view(-1, 1, 1, 1, 1) * 0}

    monkeypatch.setattr(head, "forward", inverting)
    with pytest.raises(ex.ExportError) as err:
        ex.export_model(model, batch, "onnx", tmp_path / "model.onnx")
    assert str(err.value) == (
        f"export to onnx: model.heads.occupancy ({type(head).__name__}): no ONNX translation for operation "
        "aten.linalg_inv.default, a 4x4 matrix inverse (3x3 only)"
    )
    assert list(tmp_path.iterdir()) == []  # nothing half-written


def test_streaming_graph_takes_and_returns_its_state(streaming_checkpoint, tmp_path_factory):
    """State, poses, timestamps and frame indices are graph inputs; the state comes back as an output."""
    pytest.importorskip("onnxruntime")
    onnx = pytest.importorskip("onnx")

    model, (first, second) = _restored(streaming_checkpoint)
    assert ex.is_streaming(model)
    out = _exported(streaming_checkpoint, "onnx", tmp_path_factory)  # the graph of `first`
    graph = onnx.load(str(out)).graph
    assert [i.name for i in graph.input] == [*ex.INPUTS, *ex.STREAM_INPUTS, "prev_state.scene.history"]
    assert [o.name for o in graph.output] == [*ex.OUTPUTS, "state.scene.history"]
    run = ex.load_exported(out, "onnx")
    ids, logits, state = run(*ex.example_inputs(model, first))
    assert state.shape == (1, model.scene.out_channels, *model.grid.shape)  # the fused volume F_t
    step = (*ex.inputs_of(second), *ex.stream_inputs(second, first))
    continued = run(*step, state)[1]
    other_state = run(*step, torch.zeros_like(state))[1]
    assert float((continued - other_state).abs().max()) > 1e-3  # the state input is read


def test_streaming_export_resets_as_the_eager_stream_does(streaming_checkpoint, tmp_path_factory):
    """A time gap and a frame jump restart the exported stream as they restart the eager StreamState."""
    model, (first, second) = _restored(streaming_checkpoint)
    assert model.scene.history.max_gap_s == 2.0 and model.scene.history.max_frame_step == 1
    run = ex.load_exported(_exported(streaming_checkpoint, "torch_export", tmp_path_factory), "torch_export")
    state = run(*ex.example_inputs(model, first))[2]
    fresh = run(*ex.inputs_of(second), *ex.stream_inputs(second, None), state)[1]  # is_start
    continued = run(*ex.inputs_of(second), *ex.stream_inputs(second, first), state)[1]
    assert float((continued - fresh).abs().max()) > 1e-3
    gap = dataclasses.replace(second, timestamp=second.timestamp + 10.0)  # beyond max_gap_s
    jump = dataclasses.replace(second, frame_index=second.frame_index + 1)  # a skipped frame
    back = dataclasses.replace(second, timestamp=first.timestamp)  # time does not advance
    for broken in (gap, jump, back):
        got = run(*ex.inputs_of(broken), *ex.stream_inputs(broken, first), state)[1]
        assert torch.allclose(got, fresh, atol=1e-6)
        report = ex.parity(model, run, [first, broken], "torch_export", repeats=1)  # eager resets too
        assert ex.passes(report) and report["stream"]["sequence_starts"] == 2, report
        assert report["stream"]["max_abs_state_diff"] <= 1e-4
    report = ex.parity(model, run, [first, second], "torch_export", repeats=2)  # the stream continues
    assert ex.passes(report) and report["stream"]["sequence_starts"] == 2 and report["frames_perturbed"] == 2
    assert report["stream"]["states"] == ["scene.history"]
    assert model.scene.history.slots("predict") == {}  # the eager state is left as it was


def test_state_outside_a_stream_state_is_refused():
    cfg = runner.load_config([BASELINE, "occplug/trainer/debug"], ["data.preset=tiny", *STREAMING])
    _, model = runner.build_run(cfg)
    ex.check_exportable(model)  # a StreamState is exportable
    model.scene.history = {}  # state kept some other way
    with pytest.raises(ex.ExportError) as err:
        ex.check_exportable(model)
    assert str(err.value) == (
        "model.scene (DenseVoxelsHistory) is stateful but keeps its state outside an occplug.streams.StreamState; "
        "export takes a stream's state only through StreamState"
    )


def test_index_add_exports_as_scatter_add_with_the_same_sums():
    g = torch.Generator().manual_seed(0)
    out = torch.randn(4, 5, 3, generator=g, dtype=torch.float64)
    src = torch.randn(4, 40, 3, generator=g, dtype=torch.float64)
    index = torch.randint(0, 5, (40,), generator=g)  # duplicates: the case onnxruntime's ScatterND races on
    got = _index_add_as_scatter_add(out, -2, index, src)
    assert torch.equal(got, out.index_add(1, index, src))  # the same sums in the same order: bit for bit
    got = _index_add_as_scatter_add(out, 1, index, src, alpha=-2.5)
    assert torch.allclose(got, out.index_add(1, index, src, alpha=-2.5), rtol=0, atol=1e-13)


def test_racy_accumulation_is_refused_with_one_line(baseline_checkpoint, monkeypatch, tmp_path):
    """``index_put(accumulate=True)`` becomes ``ScatterND(reduction=add)``: a different result per onnxruntime run."""
    if importlib.util.find_spec("onnxscript") is None:
        pytest.skip("the export extra (onnx, onnxruntime, onnxscript) is not installed")
    model, (batch,) = _restored(baseline_checkpoint, frames=1)
    head = model.heads[model.occupancy_head]
    forward = head.forward

    def accumulating(scene, batch):
        out = forward(scene, batch)
        logits = out["logits"]
        flat = logits.reshape(-1)
        index = torch.zeros(8, dtype=torch.int64)  # eight updates of one element
        flat = flat.index_put((index,), flat[:8] * 0, accumulate=True)
        return {"logits": flat.view_as(logits)}

    monkeypatch.setattr(head, "forward", accumulating)
    with pytest.raises(ex.ExportError) as err:
        ex.export_model(model, batch, "onnx", tmp_path / "model.onnx")
    assert str(err.value).startswith("export to onnx: ScatterND(reduction=add) ")
    assert "races on duplicate indices" in str(err.value) and "\n" not in str(err.value)
    assert list(tmp_path.iterdir()) == []  # nothing half-written


def test_inverse3_matches_linalg_inv():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(5, 2, 3, 3, generator=g, dtype=torch.float64) + 3 * torch.eye(3, dtype=torch.float64)
    inv, info = _inverse3(a)
    assert torch.allclose(inv, torch.linalg.inv(a), atol=1e-12) and info.shape == (5, 2) and not info.any()
    k = torch.tensor([[500.0, 0.0, 320.0], [0.0, 400.0, 240.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    expected = torch.tensor([[1 / 500, 0.0, -320 / 500], [0.0, 1 / 400, -240 / 400], [0.0, 0.0, 1.0]], dtype=torch.float64)
    assert torch.allclose(_inverse3(k)[0], expected, atol=1e-15)


def test_perturb_flips_and_scales_about_the_centre():
    from occplug.testing import hand_batch

    batch = hand_batch(2, cameras=3, image_hw=(8, 12))
    b, n, _, h, w = batch.images.shape
    moved = ex.perturb(batch, seed=0)
    assert torch.equal(moved.images, batch.images.flip(-1))
    aug = moved.img_aug.float() @ torch.linalg.inv(batch.img_aug.float())  # the added augmentation
    centre = torch.tensor([(w - 1) / 2, (h - 1) / 2, 1.0])
    assert torch.allclose(aug @ centre, centre.expand(b, n, 3), atol=1e-4)  # the centre stays
    left = aug @ torch.tensor([0.0, (h - 1) / 2, 1.0])
    scale = -aug[..., 0, 0]
    assert torch.allclose(left[..., 0], (w - 1) / 2 * (1 + scale), atol=1e-4)  # the left edge goes right
    assert (scale > 0.89).all() and (scale < 1.11).all()
    ratio = moved.intrinsics[..., 0, 0] / batch.intrinsics[..., 0, 0]
    assert (ratio - 1).abs().max() <= 0.08 + 1e-6 and not torch.equal(moved.intrinsics, batch.intrinsics)


def test_cli_user_mistakes(tmp_path, capsys):
    """Every path is checked before the checkpoint is read (tests/cli/test_bad_paths.py has the whole table)."""
    missing = tmp_path / "none.ckpt"
    assert main(["export", "--ckpt", str(missing), "--format", "onnx", "--out", str(tmp_path / "m.onnx")]) == 2
    assert capsys.readouterr().err.strip() == f"error: --ckpt {missing}: no such file (it does not exist)"
    ckpt = tmp_path / "some.ckpt"
    ckpt.write_text("never read\n")
    assert main(["export", "--ckpt", str(ckpt), "--format", "onnx", "--out", str(tmp_path)]) == 2
    assert capsys.readouterr().err.strip() == f"error: --out {tmp_path}: is a folder; expected a file"
    deep = tmp_path / "no" / "m.onnx"
    assert main(["export", "--ckpt", str(ckpt), "--format", "onnx", "--out", str(deep)]) == 2
    assert capsys.readouterr().err.strip() == f"error: --out {deep}: its folder {deep.parent} does not exist"
    (tmp_path / "file").write_text("x")
    below = tmp_path / "file" / "m.onnx"
    assert main(["export", "--ckpt", str(ckpt), "--format", "onnx", "--out", str(below)]) == 2
    assert capsys.readouterr().err.strip() == f"error: --out {below}: {below.parent} is a file, not a folder"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "some.ckpt"]
    with pytest.raises(ex.ExportError, match="is not a folder"):  # the library's own check says it too
        ex.export_checkpoint(ckpt, "onnx", below)


def test_parity_outside_the_thresholds_exits_1(checkpoint, tmp_path, tmp_path_factory, monkeypatch, capsys):
    """The artefact and its report stay for inspection; the command says which thresholds failed.

    The command's export is the checkpoint's artefact copied (test_export_parity runs the real one): what is checked
    here is what follows a failed parity."""
    artefact = _exported(checkpoint, "torch_export", tmp_path_factory)

    def copy_artefact(model, template, fmt, out):
        assert fmt == "torch_export" and template.images.shape[0] == 1
        shutil.copyfile(artefact, out)

    def bad_parity(model, exported, batches, fmt, repeats=3):
        return {"format": fmt, "frames": len(batches), "frames_perturbed": len(batches), "voxels": 10,
                "max_abs_logit_diff": 0.5, "class_agreement": 0.9, "eager_latency_ms": 1.0,
                "exported_latency_ms": 1.0, "versions": {"torch": torch.__version__}}

    monkeypatch.setattr("occplug.export.checkpoint.parity", bad_parity)
    monkeypatch.setattr("occplug.export.checkpoint.export_model", copy_artefact)
    out = tmp_path / "model.pt2"
    assert main(["export", "--ckpt", str(checkpoint), "--format", "torch_export", "--out", str(out)]) == 1
    captured = capsys.readouterr()
    assert captured.out.startswith("parity torch_export: ") and "classes agree on 90.0000 %" in captured.out
    assert captured.err.strip() == (
        "error: the exported model disagrees with the eager one beyond the thresholds (classes agree on >= 99.99 %, "
        f"max |logit diff| <= 0.0001); see {tmp_path / 'model.pt2.parity.json'}"
    )
    assert json.loads((tmp_path / "model.pt2.parity.json").read_text())["passed"] is False and out.is_file()
