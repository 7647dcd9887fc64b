"""Export of a model's inference path (``torch.export`` or ONNX) and the parity check against the eager model.

The exported graph is :class:`InferenceWrapper`: the camera inputs of one frame -> class ids and
logits on the evaluation grid. Calibration and image augmentation are graph **inputs**, and the
geometry that depends on them (frustum points, voxel indices) is recomputed inside the graph, so
one export serves any camera rig of the same image size and camera count.

The lift-splat splat (:class:`occplug.ops.FrustumSplatter`) normally pools through plans cached
per geometry: the cache key is a hash of the calibration's bytes, computed on the host. That step
cannot be traced: ``torch.export`` stops at it (a data-dependent guard on the depth-centre check,
then the host copy for the hash), so a cached plan can never end up in a graph as a constant.
While exporting, every splatter runs its ``reference`` path instead (the same frustum geometry,
pooled with ``index_add_`` over all points: equal up to float summation order), which is plain
tensor code on the inputs. The parity check runs the eager model with its own (cached) path on
the original frames and on frames with perturbed intrinsics, extrinsics and image augmentation,
so an export that baked one rig's geometry in would fail it.

A component that carries state from frame to frame (``stateful = True``, see
:mod:`occplug.streams`) is refused with one line naming it; streaming export (state as explicit
inputs and outputs) is not implemented yet.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import logging
import math
import os
import re
import statistics
import time
import traceback
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from occplug.data.frame import Batch
from occplug.errors import UserError
from occplug.interfaces.model import OccupancyModel
from occplug.ops.splat import FrustumSplatter
from occplug.streams import is_stateful

__all__ = [
    "FORMATS",
    "INPUTS",
    "ExportError",
    "InferenceWrapper",
    "export_checkpoint",
    "export_model",
    "export_ready",
    "load_exported",
    "occupancy_logits",
    "parity",
    "perturb",
    "report_path",
]

#: ``--format`` values and the artefact each writes.
FORMATS = ("torch_export", "onnx")

#: Graph inputs, in order (shapes of a batch of ``B`` frames with ``N`` cameras of ``H x W``):
#: ``images (B, N, 3, H, W)`` float32, ``intrinsics (B, N, 3, 3)`` float32, ``cam_to_ego
#: (B, N, 4, 4)`` float32 (camera -> ego), ``img_aug (B, N, 3, 3)`` float32 (original -> augmented pixel).
INPUTS = ("images", "intrinsics", "cam_to_ego", "img_aug")

#: Graph outputs: ``class_ids (B, X, Y, Z)`` int64 and ``logits (B, K, X, Y, Z)`` float32, ego frame, evaluation grid.
OUTPUTS = ("class_ids", "logits")

#: Fields of a batch the exported graph takes as inputs; a model reading any other optional field is refused.
_SUPPORTED_FIELDS = frozenset(INPUTS)


class ExportError(UserError):
    """A model or component that cannot be exported; ``str(err)`` is one line naming it and the operation."""


# ---------------------------------------------------------------------------------------------- the graph
def occupancy_logits(model: nn.Module, outputs: Any) -> Tensor:
    """``(B, K, X, Y, Z)`` logits on ``model.grid`` of a forward pass, the logits whose argmax is
    :meth:`~occplug.model.OccModel.occupancy_from` (same rule: the occupancy head's forward logits
    where they live on the evaluation grid, else the head's ``occupancy_logits`` at its voxel centres)."""
    if hasattr(model, "occupancy_logits_from"):  # a model class that says itself
        return model.occupancy_logits_from(outputs)
    head_name = getattr(model, "occupancy_head", None)
    heads = getattr(model, "heads", None)
    if head_name is None or heads is None or head_name not in heads:
        raise ExportError(
            f"model ({type(model).__name__}) has no occupancy head to export; export needs heads[occupancy_head] "
            "or an occupancy_logits_from(outputs) method"
        )
    logits = outputs.heads[head_name].get("logits")
    if (
        logits is not None
        and getattr(outputs.scene, "grid", None) == model.grid
        and tuple(logits.shape[2:]) == model.grid.shape
    ):
        return logits
    return heads[head_name].occupancy_logits(outputs.scene, model.grid)


class InferenceWrapper(nn.Module):
    """The exported function: one model's inference path on plain tensors (see :data:`INPUTS`, :data:`OUTPUTS`).

    Args:
        model: an :class:`~occplug.interfaces.model.OccupancyModel` (e.g. ``OccModel``) in eval mode.
        template: a :class:`~occplug.data.Batch` supplying every field that is not an input (scene
            names, tokens, frame indices, ...); its tensor inputs only fix the shapes.

    Forward:
        ``images, intrinsics, cam_to_ego, img_aug`` -> ``(class_ids (B, X, Y, Z) int64, logits
        (B, K, X, Y, Z) float32)`` on the evaluation grid in the ego frame.
    """

    def __init__(self, model: nn.Module, template: Batch) -> None:
        super().__init__()
        self.model = model
        self.template = template

    def forward(self, images: Tensor, intrinsics: Tensor, cam_to_ego: Tensor, img_aug: Tensor) -> tuple[Tensor, Tensor]:
        batch = dataclasses.replace(
            self.template, images=images, intrinsics=intrinsics, cam_to_ego=cam_to_ego, img_aug=img_aug
        )
        logits = occupancy_logits(self.model, self.model(batch))
        return logits.argmax(dim=1), logits


def inputs_of(batch: Batch) -> tuple[Tensor, ...]:
    """The graph inputs (:data:`INPUTS`) of ``batch``, float32 and contiguous."""
    return tuple(getattr(batch, name).float().contiguous() for name in INPUTS)


@contextlib.contextmanager
def export_ready(model: nn.Module) -> Iterator[None]:
    """Run every :class:`~occplug.ops.FrustumSplatter` of ``model`` on its traceable ``reference`` path inside.

    The ``fast`` path's plan cache is keyed by a host-side hash of the calibration (see the module
    docstring); the reference path computes the same frustum geometry from the input tensors.
    """
    splatters = [v for sub in model.modules() for v in vars(sub).values() if isinstance(v, FrustumSplatter)]
    modes = [s.mode for s in splatters]
    try:
        for s in splatters:
            s.mode = "reference"
        yield
    finally:
        for s, mode in zip(splatters, modes, strict=True):
            s.mode = mode


def check_exportable(model: nn.Module) -> None:
    """Refuse, in one line, a model the exported graph cannot represent.

    Raises:
        ExportError: a stateful component (streaming export is not implemented), or an inference
            component reading a batch field that is no graph input (e.g. LiDAR ``points``).
    """
    for name, sub in model.named_modules():
        if name and is_stateful(sub):
            raise ExportError(
                f"model.{name} ({type(sub).__name__}) is stateful (it carries features from frame to frame); "
                "export of streaming models (state as explicit inputs and outputs) is not supported yet"
            )
    supervision = {id(m) for s in (getattr(model, "supervision", None) or {}).values() for m in s.modules()}
    for name, sub in model.named_modules():
        extra = set(getattr(sub, "requires", ()) or ()) - _SUPPORTED_FIELDS
        if extra and id(sub) not in supervision:  # supervision is not part of inference
            raise ExportError(
                f"model.{name} ({type(sub).__name__}) reads batch field(s) {', '.join(sorted(extra))}; the exported "
                f"graph takes only {', '.join(INPUTS)}"
            )


# ---------------------------------------------------------------------------------------------- failures
def _module_names(model: nn.Module) -> dict[int, str]:
    return {id(m): (f"model.{n}" if n else "model") for n, m in model.named_modules()}


def _describe_component(names: dict[int, str], module: nn.Module) -> str:
    return f"{names.get(id(module), 'model')} ({type(module).__name__})"


def _first_line(exc: BaseException) -> str:
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return lines[0] if lines else type(exc).__name__


def _trace_failure(exc: BaseException, model: nn.Module) -> ExportError:
    """One line naming the innermost model component on the failing call stack and the failing line."""
    names = _module_names(model)
    component: nn.Module = model
    where = ""
    skipped = (os.path.dirname(torch.__file__), os.path.dirname(contextlib.__file__), __file__)
    for frame, lineno in traceback.walk_tb(exc.__traceback__):
        owner = frame.f_locals.get("self")
        if isinstance(owner, nn.Module) and id(owner) in names:
            component = owner
        path = frame.f_code.co_filename
        if not path.startswith(skipped[:2]) and path != skipped[2] and "/lightning" not in path:
            where = f"{Path(path).name}:{lineno} {_source_line(path, lineno)}"
    reason = _first_line(exc)
    if "data-dependent" in reason:
        reason = f"data-dependent control flow ({reason})"
    op = f" at {where}" if where else ""
    return ExportError(f"export: {_describe_component(names, component)} cannot be traced{op}: {reason}")


def _source_line(path: str, lineno: int) -> str:
    import linecache

    return "`" + linecache.getline(path, lineno).strip() + "`"


def _onnx_failure(exc: BaseException, program: torch.export.ExportedProgram, model: nn.Module) -> ExportError:
    """One line naming the operation ONNX has no translation for and the component whose graph node holds it."""
    found = re.search(r"OpOverload\(op='([^']+)'", str(exc))
    op = exc.op if isinstance(exc, _NoOnnxTranslation) else found.group(1) if found else None
    component = "model"
    if op is not None:
        base = op.split(".")[1] if op.count(".") >= 1 else op  # aten.linalg_inv_ex.default -> linalg_inv_ex
        for node in program.graph.nodes:
            name = str(node.target).split(".")
            if node.op != "call_function" or len(name) < 2 or not base.startswith(name[1]):
                continue
            shape = getattr(exc, "shape", None)
            arg = node.args[0] if node.args else None
            if shape is not None and tuple(getattr(getattr(arg, "meta", {}).get("val"), "shape", ())) != shape:
                continue
            stack = node.meta.get("nn_module_stack") or {}
            if stack:
                path, cls = list(stack.values())[-1]
                path = re.sub(r"^(L\['self'\]\.)?", "", str(path)).removeprefix("model.")
                cls_name = getattr(cls, "__name__", str(cls).rsplit(".", 1)[-1].strip("'>"))
                component = f"model.{path} ({cls_name})" if path else "model"
            break
    what = f"operation {op}" if op else _first_line(exc)
    if isinstance(exc, _NoOnnxTranslation):
        what += f", {exc.what}"
    return ExportError(f"export to onnx: {component}: no ONNX translation for {what}")


# ---------------------------------------------------------------------------------------------- export
class _NoOnnxTranslation(Exception):
    def __init__(self, op: str, what: str, shape: tuple[int, ...] | None = None) -> None:
        super().__init__(what)
        self.op, self.what, self.shape = op, what, shape


def _inverse3(a: Tensor) -> tuple[Tensor, Tensor]:
    """Inverse of ``(..., 3, 3)`` matrices by the adjugate (ONNX has no matrix inverse); ``(inverse, info)``."""
    if tuple(a.shape[-2:]) != (3, 3):
        what = f"a {a.shape[-2]}x{a.shape[-1]} matrix inverse (3x3 only)"
        raise _NoOnnxTranslation("aten.linalg_inv.default", what, tuple(a.shape))
    m = [[a[..., i, j] for j in range(3)] for i in range(3)]

    def cof(i: int, j: int) -> Tensor:
        r = [k for k in range(3) if k != i]
        c = [k for k in range(3) if k != j]
        minor = m[r[0]][c[0]] * m[r[1]][c[1]] - m[r[0]][c[1]] * m[r[1]][c[0]]
        return minor if (i + j) % 2 == 0 else -minor

    cofactors = [[cof(i, j) for j in range(3)] for i in range(3)]
    det = m[0][0] * cofactors[0][0] + m[0][1] * cofactors[0][1] + m[0][2] * cofactors[0][2]
    adjugate = torch.stack([torch.stack([cofactors[j][i] for j in range(3)], -1) for i in range(3)], -2)
    return adjugate / det[..., None, None], torch.zeros(a.shape[:-2], dtype=torch.int32, device=a.device)


def _onnx_decompositions() -> dict[Any, Callable[..., Any]]:
    aten = torch.ops.aten
    return {aten.linalg_inv.default: lambda a: _inverse3(a)[0], aten.linalg_inv_ex.default: _inverse3}


def trace(model: OccupancyModel, template: Batch) -> torch.export.ExportedProgram:
    """``torch.export`` of :class:`InferenceWrapper` on ``template``'s shapes (raises :class:`ExportError`)."""
    check_exportable(model)
    wrapper = InferenceWrapper(model, template).eval()
    with export_ready(model), torch.no_grad(), _quiet():
        try:
            return torch.export.export(wrapper, inputs_of(template))
        except ExportError:
            raise
        except Exception as exc:  # torch.export raises many types; all mean "this code cannot be traced"
            raise _trace_failure(exc, model) from None


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """Keep the exporters' progress prints and warnings off the console."""
    disabled = logging.root.manager.disable
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        warnings.simplefilter("ignore")
        logging.disable(logging.WARNING)  # torch logs whole graphs as warnings when tracing fails
        try:
            yield
        finally:
            logging.disable(disabled)


def export_model(model: OccupancyModel, template: Batch, fmt: str, out: Path) -> torch.export.ExportedProgram:
    """Export ``model``'s inference path for ``template``'s shapes into ``out`` (written atomically).

    ``torch_export`` writes a ``torch.export.save`` archive (``.pt2``); ``onnx`` an ONNX model (the
    ``export`` extra: onnx, onnxscript). Returns the traced program.
    """
    if fmt not in FORMATS:
        raise ExportError(f"--format: {fmt!r} is not one of {', '.join(FORMATS)}")
    program = trace(model, template)
    out = Path(out)
    tmp = out.with_name(f".{out.stem}.tmp{out.suffix}")  # keeps the suffix torch.export.save checks
    try:
        if fmt == "torch_export":
            torch.export.save(program, str(tmp))
        else:
            _require("onnx", "onnxscript")
            with _quiet():
                try:
                    onnx_program = torch.onnx.export(
                        program.run_decompositions(_onnx_decompositions()), inputs_of(template),
                        input_names=list(INPUTS), output_names=list(OUTPUTS), dynamo=True, verbose=False,
                    )
                except ExportError:
                    raise
                except Exception as exc:
                    raise _onnx_failure(exc, program, model) from None
                onnx_program.save(str(tmp), external_data=False)  # one self-contained file
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return program


def _require(*modules: str) -> None:
    import importlib.util

    missing = [m for m in modules if importlib.util.find_spec(m) is None]
    if missing:
        raise ExportError(
            f"export to onnx needs {', '.join(missing)}; pip install 'occplug[export]' (onnx, onnxruntime, onnxscript)"
        )


def load_exported(path: Path, fmt: str) -> Callable[..., tuple[Tensor, Tensor]]:
    """The artefact at ``path`` as a function of :data:`INPUTS` -> ``(class_ids, logits)`` torch tensors.

    ``torch_export``: ``torch.export.load(...).module()``; ``onnx``: an onnxruntime CPU session.
    """
    if fmt == "torch_export":
        module = torch.export.load(str(path)).module()

        def run_program(*args: Tensor) -> tuple[Tensor, Tensor]:
            with torch.no_grad():
                ids, logits = module(*args)
            return ids, logits

        return run_program
    _require("onnxruntime")
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.log_severity_level = 3
    # no busy-waiting pool threads after a run: they would steal the CPU from the eager model timed beside it
    options.intra_op_num_threads = torch.get_num_threads()
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    names = [i.name for i in session.get_inputs()]

    def run_session(*args: Tensor) -> tuple[Tensor, Tensor]:
        ids, logits = session.run(list(OUTPUTS), {n: a.numpy() for n, a in zip(names, args, strict=True)})
        return torch.from_numpy(ids), torch.from_numpy(logits)

    return run_session


# ---------------------------------------------------------------------------------------------- parity
def perturb(batch: Batch, seed: int) -> Batch:
    """``batch`` seen by another rig: perturbed intrinsics and extrinsics, and an image augmentation.

    Focal lengths scale by up to +-8 %, the principal point moves by up to 4 % of the image size,
    every camera turns by up to 2 degrees of yaw and moves by up to 0.2 m, and the images are
    flipped left-right and rescaled about the centre by up to 10 %, recorded in ``img_aug`` (the
    flip mirrors the image tensor too, so image and calibration stay consistent).
    """
    g = torch.Generator().manual_seed(int(seed))
    b, n, _, h, w = batch.images.shape

    def u(*shape: int) -> Tensor:
        return torch.rand(*shape, generator=g) * 2 - 1

    k = batch.intrinsics.clone().float()
    k[..., 0, 0] *= 1 + 0.08 * u(b, n)
    k[..., 1, 1] *= 1 + 0.08 * u(b, n)
    k[..., 0, 2] += 0.04 * w * u(b, n)
    k[..., 1, 2] += 0.04 * h * u(b, n)
    yaw = math.radians(2.0) * u(b, n)
    turn = torch.eye(4).repeat(b, n, 1, 1)
    turn[..., 0, 0], turn[..., 0, 1] = torch.cos(yaw), -torch.sin(yaw)
    turn[..., 1, 0], turn[..., 1, 1] = torch.sin(yaw), torch.cos(yaw)
    turn[..., :3, 3] = 0.2 * u(b, n, 3)
    cam_to_ego = turn @ batch.cam_to_ego.float()
    scale = 1 + 0.1 * u(b, n)
    aug = torch.eye(3).repeat(b, n, 1, 1)  # pixel u -> (w - 1) - u, then scale about the image centre
    aug[..., 0, 0], aug[..., 0, 2] = -scale, (w - 1) / 2 * (1 + scale)
    aug[..., 1, 1], aug[..., 1, 2] = scale, (h - 1) / 2 * (1 - scale)
    img_aug = aug @ batch.img_aug.float()
    return dataclasses.replace(
        batch, images=batch.images.flip(-1).contiguous(), intrinsics=k, cam_to_ego=cam_to_ego, img_aug=img_aug
    )


def report_path(out: Path) -> Path:
    """Where the parity report of artefact ``out`` goes: ``<out>.parity.json`` beside it."""
    out = Path(out)
    return out.with_name(out.name + ".parity.json")


def _versions(fmt: str) -> dict[str, str | None]:
    out: dict[str, str | None] = {"torch": torch.__version__}
    if fmt == "onnx":
        for name in ("onnx", "onnxruntime", "onnxscript"):
            try:
                out[name] = __import__(name).__version__
            except ImportError:
                out[name] = None
    return out


def parity(
    model: OccupancyModel,
    exported: Callable[..., tuple[Tensor, Tensor]],
    batches: Sequence[Batch],
    fmt: str,
    repeats: int = 3,
) -> dict[str, Any]:
    """Compare the eager model with an exported one on ``batches`` (each also :func:`perturb`-ed).

    The eager side is the model as it runs in ``validate``/``predict`` (fast splat with cached
    plans); the exported side gets the same tensors. Latencies are the median over frames of the
    best of ``repeats`` calls (the first call of each side is a warm-up), milliseconds per call.

    Returns:
        ``{"format", "frames", "frames_perturbed", "voxels", "max_abs_logit_diff", "class_agreement"
        (share of voxels whose class ids agree, in [0, 1]), "eager_latency_ms", "exported_latency_ms",
        "versions"}``.
    """
    model.eval()
    frames = [f for i, batch in enumerate(batches) for f in (batch, perturb(batch, seed=i))]
    max_diff, agree, voxels = 0.0, 0, 0
    eager_ms: list[float] = []
    exported_ms: list[float] = []
    with torch.no_grad():
        for batch in frames[:1]:  # warm-up (first calls allocate, build plans)
            model.predict_occupancy(batch)
            exported(*inputs_of(batch))
        for batch in frames:
            args = inputs_of(batch)
            eager_t, got_t = [], []
            for _ in range(max(1, repeats)):
                t0 = time.perf_counter()
                outputs = model(batch)
                eager_ids = model.occupancy_from(outputs) if hasattr(model, "occupancy_from") else None
                eager_logits = occupancy_logits(model, outputs)
                t1 = time.perf_counter()
                ids, logits = exported(*args)
                t2 = time.perf_counter()
                eager_t.append(t1 - t0)
                got_t.append(t2 - t1)
            if eager_ids is None:
                eager_ids = eager_logits.argmax(dim=1)
            eager_ms.append(min(eager_t) * 1e3)
            exported_ms.append(min(got_t) * 1e3)
            max_diff = max(max_diff, float((logits.float() - eager_logits.float()).abs().max()))
            agree += int((ids.long() == eager_ids.long()).sum())
            voxels += int(eager_ids.numel())
    return {
        "format": fmt,
        "frames": len(batches),
        "frames_perturbed": len(frames) - len(batches),
        "voxels": voxels,
        "max_abs_logit_diff": max_diff,
        "class_agreement": agree / max(voxels, 1),
        "eager_latency_ms": statistics.median(eager_ms),
        "exported_latency_ms": statistics.median(exported_ms),
        "versions": _versions(fmt),
    }


#: What the baseline reaches (README, Export); ``occplug export`` fails a report outside them.
MIN_CLASS_AGREEMENT = 0.9999
MAX_LOGIT_DIFF = 1e-4


def passes(report: dict[str, Any]) -> bool:
    """Whether a :func:`parity` report is within :data:`MIN_CLASS_AGREEMENT` and :data:`MAX_LOGIT_DIFF`."""
    return report["class_agreement"] >= MIN_CLASS_AGREEMENT and report["max_abs_logit_diff"] <= MAX_LOGIT_DIFF


def one_line(report: dict[str, Any]) -> str:
    """The report as the one line ``occplug export`` prints."""
    versions = " ".join(f"{k}={v}" for k, v in report["versions"].items())
    return (
        f"parity {report['format']}: {report['frames']} frames + {report['frames_perturbed']} perturbed, "
        f"classes agree on {100 * report['class_agreement']:.4f} % of {report['voxels']} voxels, "
        f"max |logit diff| {report['max_abs_logit_diff']:.3g}, latency eager {report['eager_latency_ms']:.1f} ms "
        f"vs exported {report['exported_latency_ms']:.1f} ms ({versions})"
    )


def export_checkpoint(ckpt: Path, fmt: str, out: Path, samples: int = 4) -> dict[str, Any]:
    """``occplug export``: rebuild the model from ``ckpt`` alone, export it to ``out``, check parity.

    The first ``samples`` frames of the checkpoint's validation split (then of its training split,
    where the validation split is shorter), batch size 1, are the parity frames; the first fixes the
    exported shapes (batch size 1, camera count, image size). Writes the report (:func:`parity`, plus
    ``checkpoint``, ``artefact`` and ``passed``) to :func:`report_path` and returns it.

    Raises:
        ExportError / RunError: one line (a bad path, a component that cannot be exported, ...).
    """
    from occplug import runner

    ckpt, out = Path(ckpt), Path(out)
    if fmt not in FORMATS:
        raise ExportError(f"--format: {fmt!r} is not one of {', '.join(FORMATS)}")
    if samples < 1:
        raise ExportError(f"--samples: must be >= 1, got {samples}")
    check_out(out)
    cfg = runner.resolve_run_config([], [], ckpt)
    dm, model = runner._restore(cfg, runner.load_checkpoint(ckpt), ckpt)
    model.eval()
    batches: list[Batch] = []
    with runner._data_errors():
        for split in ("val", "train"):  # a small validation split is topped up with training frames
            dataset = dm.dataset(split)
            take = min(int(samples) - len(batches), len(dataset))  # type: ignore[arg-type]
            batches += [dm.collate([dataset[i]]) for i in range(max(take, 0))]
    if not batches:
        raise ExportError("data: the validation and training splits are empty; nothing to check the export on")
    export_model(model, batches[0], fmt, out)
    report = parity(model, load_exported(out, fmt), batches, fmt)
    report = {"checkpoint": str(ckpt), "artefact": str(out), **report, "passed": passes(report)}
    runner.write_json(report_path(out), report)
    return report


def check_out(out: Path) -> None:
    """Raise one line when ``--out`` cannot take the artefact (a folder, a missing or non-folder parent)."""
    if out.is_dir():
        raise ExportError(f"--out {out}: is a folder; give the artefact's file name (e.g. {out / 'model.onnx'})")
    parent = out.parent
    if not parent.exists():
        raise ExportError(f"--out {out}: folder {parent} does not exist")
    if not parent.is_dir():
        raise ExportError(f"--out {out}: {parent} is not a folder")
    if not os.access(parent, os.W_OK):
        raise ExportError(f"--out {out}: folder {parent} is not writable")
