"""Tracing the graph (:func:`trace`), writing it as a ``torch.export`` archive or an ONNX model (:func:`export_model`)
and loading an artefact back as a function (:func:`load_exported`).

Also what ONNX needs beyond ``torch.export``: decompositions of the operations it has no translation for (a 3x3
matrix inverse by the adjugate, ``index_add`` as ``scatter_add``), the refusal of a graph holding an operation whose
onnxruntime CPU kernel races, and the one-line explanations of a failed trace or translation, naming the component.
"""

from __future__ import annotations

import contextlib
import os
import re
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from occplug.data.frame import Batch
from occplug.interfaces.model import OccupancyModel

from .graph import FORMATS, ExportError, _Graph, _graph, _quiet


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
    skipped = (os.path.dirname(torch.__file__), os.path.dirname(contextlib.__file__))
    package = os.path.dirname(__file__) + os.sep  # occplug.export's own modules (the wrappers, the stand-ins)
    for frame, lineno in traceback.walk_tb(exc.__traceback__):
        owner = frame.f_locals.get("self")
        if isinstance(owner, nn.Module) and id(owner) in names:
            component = owner
        path = frame.f_code.co_filename
        if not path.startswith(skipped) and not path.startswith(package) and "/lightning" not in path:
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


def _index_add_as_scatter_add(self: Tensor, dim: int, index: Tensor, source: Tensor, alpha: float = 1) -> Tensor:
    """``index_add`` as ``scatter_add`` (ONNX ``ScatterElements``): the same sums in the same order.

    ``index_add`` becomes ``ScatterND(reduction="add")``, whose onnxruntime CPU kernel races on
    duplicate indices with more than one thread (microsoft/onnxruntime#18048, #23396: lost updates,
    a different result every run); a splat's indices are all duplicates.
    """
    dim = dim % source.dim()
    shape = [1] * source.dim()
    shape[dim] = -1
    return self.scatter_add(dim, index.reshape(shape).expand_as(source), source if alpha == 1 else source * alpha)


def _onnx_decompositions() -> dict[Any, Callable[..., Any]]:
    aten = torch.ops.aten
    return {
        aten.linalg_inv.default: lambda a: _inverse3(a)[0],
        aten.linalg_inv_ex.default: _inverse3,
        aten.index_add.default: _index_add_as_scatter_add,
    }


#: ONNX ops whose onnxruntime CPU kernel is not deterministic with duplicate indices (see above).
_RACY_ONNX = {"ScatterND": "reduction"}


def _racy_nodes(model_proto: Any) -> list[str]:
    """Nodes of an ONNX graph (subgraphs included) that onnxruntime's CPU kernels compute with a race."""
    found = []
    graphs = [model_proto.graph]
    while graphs:
        graph = graphs.pop()
        for node in graph.node:
            attrs = {a.name: a for a in node.attribute}
            graphs.extend(a.g for a in node.attribute if a.HasField("g"))
            attr = _RACY_ONNX.get(node.op_type)
            if attr and attr in attrs and attrs[attr].s not in (b"", b"none"):
                found.append(f"{node.op_type}({attr}={attrs[attr].s.decode()}) {node.name}")
    return found


def trace(model: OccupancyModel, template: Batch) -> torch.export.ExportedProgram:
    """``torch.export`` of :class:`InferenceWrapper` (a streaming model: :class:`StreamingWrapper`) on
    ``template``'s shapes (raises :class:`ExportError`)."""
    with _graph(model, template) as graph:
        return _trace(graph, model)


def _trace(graph: _Graph, model: nn.Module) -> torch.export.ExportedProgram:
    with torch.no_grad(), _quiet():
        try:
            return torch.export.export(graph.wrapper, graph.args, dynamic_shapes=graph.dynamic_shapes)
        except ExportError:
            raise
        except Exception as exc:  # torch.export raises many types; all mean "this code cannot be traced"
            raise _trace_failure(exc, model) from None


def export_model(model: OccupancyModel, template: Batch, fmt: str, out: Path) -> torch.export.ExportedProgram:
    """Export ``model``'s inference path for ``template``'s shapes into ``out`` (written atomically).

    ``torch_export`` writes a ``torch.export.save`` archive (``.pt2``); ``onnx`` an ONNX model (the
    ``export`` extra: onnx, onnxscript). Returns the traced program.
    """
    if fmt not in FORMATS:
        raise ExportError(f"--format: {fmt!r} is not one of {', '.join(FORMATS)}")
    out = Path(out)
    tmp = out.with_name(f".{out.stem}.tmp{out.suffix}")  # keeps the suffix torch.export.save checks
    try:
        with _graph(model, template) as graph:
            program = _trace(graph, model)
            if fmt == "torch_export":
                torch.export.save(program, str(tmp))
            else:
                _require("onnx", "onnxscript")
                with _quiet():
                    try:
                        onnx_program = torch.onnx.export(
                            program.run_decompositions(_onnx_decompositions()), graph.args,
                            input_names=graph.input_names, output_names=graph.output_names, dynamo=True,
                            verbose=False,
                        )
                    except ExportError:
                        raise
                    except Exception as exc:
                        raise _onnx_failure(exc, program, model) from None
                    racy = _racy_nodes(onnx_program.model_proto)
                    if racy:
                        raise ExportError(
                            f"export to onnx: {racy[0]}: onnxruntime's CPU kernel races on duplicate indices "
                            "(a different result every run); accumulate with scatter_add/index_add, not index_put"
                        )
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


def load_exported(path: Path, fmt: str) -> Callable[..., tuple[Tensor, ...]]:
    """The artefact at ``path`` as a function of its inputs (:data:`INPUTS`; a streaming model's also
    :data:`STREAM_INPUTS` and its state) -> its outputs as torch tensors (``class_ids, logits[, *state]``).

    ``torch_export``: ``torch.export.load(...).module()``; ``onnx``: an onnxruntime CPU session.
    """
    if fmt == "torch_export":
        module = torch.export.load(str(path)).module()

        def run_program(*args: Tensor) -> tuple[Tensor, ...]:
            with torch.no_grad():
                return tuple(module(*args))

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

    def run_session(*args: Tensor) -> tuple[Tensor, ...]:
        outputs = session.run(None, {n: a.numpy() for n, a in zip(names, args, strict=True)})
        return tuple(torch.from_numpy(o) for o in outputs)

    return run_session
