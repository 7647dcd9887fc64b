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
tensor code on the inputs. ONNX gets that ``index_add`` as ``ScatterElements`` (:func:`_index_add_as_scatter_add`):
onnxruntime's CPU ``ScatterND(reduction="add")`` races on duplicate indices, so a graph holding one is refused.
The parity check runs the eager model with its own (cached) path on
the original frames and on frames with perturbed intrinsics, extrinsics and image augmentation,
so an export that baked one rig's geometry in would fail it.

A model that reads **LiDAR** (a point encoder) also takes :data:`POINT_INPUTS`: the points, NaN-padded to
the longest cloud of the batch, with the point count a dynamic dimension, and the LiDAR -> ego pose. Its point
encoders must trace with any point count: drop points by pooling them into a discard row, not by boolean
indexing (the core's ``voxel_points`` does so), and treat non-finite rows as no point.

A **streaming** model (a component holding a :class:`occplug.streams.StreamState`) exports as
:class:`StreamingWrapper`: one step of the stream, its state an explicit input and output. Besides
:data:`INPUTS` the graph takes :data:`STREAM_INPUTS` (this frame's and the previous frame's pose,
timestamp and frame index, and ``is_start``) and the previous state (``prev_state.<name>``), and
returns the new state (``state.<name>``) after ``class_ids`` and ``logits``; feed the outputs of one
frame back as the inputs of the next (:func:`stream_inputs`). The reset rules of
:class:`~occplug.streams.StreamState` are in the graph (a frame-index step outside
``1..max_frame_step``, a time step outside ``(0, max_gap_s]``), except the one on strings: the
caller says ``is_start`` at the first frame and wherever the scene changes. Poses come in as
``ego_to_global`` float64, as the eager state keeps them, and the relative motion is computed in
float64 inside the graph as eager computes it (float32 global poses, hundreds of metres off the
origin, would round the translation before the subtraction; both exporters and onnxruntime take
float64 matmuls). While exporting, every ``StreamState`` is replaced by an :class:`ExplicitStream`
reading those inputs, and a component whose forward branches on the reset mask (``if reset.any()``,
boolean-mask indexing: data-dependent, untraceable) runs a branch-free equivalent (its own
``export_forward``, as the core's ``dense_voxels_history`` does). The parity check runs the frames as a
sequence in order (each also perturbed, as a second sequence), feeding the exported state back, and
compares the state too.

A component that declares ``stateful = True`` but keeps its state outside a ``StreamState`` is
refused with one line naming it.
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
from occplug.geometry import relative_pose
from occplug.interfaces.model import OccupancyModel
from occplug.ops.splat import FrustumSplatter
from occplug.streams import StreamRead, StreamState, _leaves, _map, is_stateful, set_stream_stage

__all__ = [
    "FORMATS",
    "INPUTS",
    "POINT_INPUTS",
    "STREAM_INPUTS",
    "ExplicitStream",
    "ExportError",
    "InferenceWrapper",
    "StreamingWrapper",
    "example_inputs",
    "export_checkpoint",
    "export_model",
    "export_ready",
    "graph_inputs",
    "inputs_of",
    "is_streaming",
    "load_exported",
    "occupancy_logits",
    "pad_points",
    "parity",
    "perturb",
    "reads_points",
    "report_path",
    "stream_inputs",
    "stream_parity",
]

#: ``--format`` values and the artefact each writes.
FORMATS = ("torch_export", "onnx")

#: Graph inputs, in order (shapes of a batch of ``B`` frames with ``N`` cameras of ``H x W``):
#: ``images (B, N, 3, H, W)`` float32, ``intrinsics (B, N, 3, 3)`` float32, ``cam_to_ego
#: (B, N, 4, 4)`` float32 (camera -> ego), ``img_aug (B, N, 3, 3)`` float32 (original -> augmented pixel).
INPUTS = ("images", "intrinsics", "cam_to_ego", "img_aug")

#: Graph outputs: ``class_ids (B, X, Y, Z)`` int64 and ``logits (B, K, X, Y, Z)`` float32, ego frame, evaluation grid.
OUTPUTS = ("class_ids", "logits")

#: Extra graph inputs of a streaming model, after :data:`INPUTS` and before one ``prev_state.<name>`` per state
#: tensor (``B`` frames): ``ego_to_global (B, 4, 4)`` float64, ``timestamp (B,)`` float64 seconds, ``frame_index
#: (B,)`` int64, ``is_start (B,)`` bool (the first frame of a stream: no previous frame, another scene), then the
#: previous frame's ``prev_ego_to_global``, ``prev_timestamp``, ``prev_frame_index`` (any values where
#: ``is_start``). Extra outputs, after :data:`OUTPUTS`: ``state.<name>``, the next frame's ``prev_state.<name>``.
STREAM_INPUTS = (
    "ego_to_global", "timestamp", "frame_index", "is_start", "prev_ego_to_global", "prev_timestamp", "prev_frame_index"
)

#: Extra graph inputs of a model that reads LiDAR (an inference component requiring ``points``), right after
#: :data:`INPUTS`: ``points (B, P, F)`` float32 in the lidar frame (x, y, z, intensity, ...; a cloud with fewer
#: than ``P`` points is padded with NaN rows, which point encoders treat as no point; ``P`` is a dynamic
#: dimension of the graph) and ``lidar_to_ego (B, 4, 4)`` float32 (:func:`pad_points` builds ``points``).
POINT_INPUTS = ("points", "lidar_to_ego")

#: Fields of a batch the exported graph takes as inputs; a model reading any other optional field is refused.
_SUPPORTED_FIELDS = frozenset(INPUTS) | frozenset(POINT_INPUTS)


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


def _supervision_modules(model: nn.Module) -> set[int]:
    """``id`` of every module inside ``model``'s supervision sources (not part of inference)."""
    return {id(m) for s in (getattr(model, "supervision", None) or {}).values() for m in s.modules()}


def reads_points(model: nn.Module) -> bool:
    """Whether an inference component of ``model`` (not its supervision) requires the batch's LiDAR ``points`` or
    ``lidar_to_ego`` (then both are graph inputs: a LiDAR pose read alone would otherwise become a constant)."""
    supervision = _supervision_modules(model)
    return any(
        set(getattr(sub, "requires", ()) or ()) & set(POINT_INPUTS) and id(sub) not in supervision
        for sub in model.modules()
    )


def graph_inputs(model: nn.Module) -> tuple[str, ...]:
    """The graph's inputs of ``model`` before any stream inputs: :data:`INPUTS`, then :data:`POINT_INPUTS` when
    it reads LiDAR (:func:`reads_points`)."""
    return (*INPUTS, *POINT_INPUTS) if reads_points(model) else INPUTS


def pad_points(clouds: Sequence[Tensor]) -> Tensor:
    """``B`` point clouds ``(P_b, F)`` -> ``(B, P, F)`` float32 on the first cloud's device, ``P = max(2, max P_b)``,
    the shorter ones padded with NaN rows (at least 2 rows: the graph's dynamic point count starts at 2)."""
    if not clouds:
        raise ValueError("pad_points: no point cloud given (a batch has at least one frame)")
    size = max(2, *(int(c.shape[0]) for c in clouds))
    out = torch.full(
        (len(clouds), size, int(clouds[0].shape[1])), float("nan"), dtype=torch.float32, device=clouds[0].device
    )
    for b, cloud in enumerate(clouds):
        out[b, : cloud.shape[0]] = cloud.float()
    return out


def _batch_of(template: Batch, names: Sequence[str], args: Sequence[Tensor], **fields: Any) -> Batch:
    """``template`` with the graph inputs ``args`` (named ``names``) and ``fields`` in place (``points`` back to
    one ``(P, F)`` tensor per frame, NaN padding rows included)."""
    given = dict(zip(names, args, strict=True))
    if "points" in given:
        given["points"] = list(given["points"].unbind(0))
    return dataclasses.replace(template, **given, **fields)


class InferenceWrapper(nn.Module):
    """The exported function: one model's inference path on plain tensors (see :data:`INPUTS`, :data:`OUTPUTS`).

    Args:
        model: an :class:`~occplug.interfaces.model.OccupancyModel` (e.g. ``OccModel``) in eval mode.
        template: a :class:`~occplug.data.Batch` supplying every field that is not an input (scene
            names, tokens, frame indices, ...); its tensor inputs only fix the shapes.
        names: the inputs, in order (:func:`graph_inputs`; default :data:`INPUTS`).

    Forward:
        ``images, intrinsics, cam_to_ego, img_aug`` (then ``points, lidar_to_ego`` when ``names`` has them) ->
        ``(class_ids (B, X, Y, Z) int64, logits (B, K, X, Y, Z) float32)`` on the evaluation grid in the ego frame.
    """

    def __init__(self, model: nn.Module, template: Batch, names: Sequence[str] = INPUTS) -> None:
        super().__init__()
        self.model = model
        self.template = template
        self.names = tuple(names)

    def forward(self, *args: Tensor) -> tuple[Tensor, Tensor]:
        batch = _batch_of(self.template, self.names, args)
        logits = occupancy_logits(self.model, self.model(batch))
        return logits.argmax(dim=1), logits


def inputs_of(batch: Batch, names: Sequence[str] = INPUTS) -> tuple[Tensor, ...]:
    """The graph inputs ``names`` (:func:`graph_inputs`; default :data:`INPUTS`) of ``batch``, float32 and
    contiguous (``points`` padded by :func:`pad_points`)."""
    return tuple(
        pad_points(batch.points) if name == "points" else getattr(batch, name).float().contiguous() for name in names
    )


# ---------------------------------------------------------------------------------------------- streaming
@dataclasses.dataclass
class _Previous:
    """The previous frame as graph inputs, shared by the :class:`ExplicitStream` of one model."""

    is_start: Tensor | None = None
    ego_to_global: Tensor | None = None
    timestamp: Tensor | None = None
    frame_index: Tensor | None = None


class ExplicitStream:
    """Stand-in for a :class:`~occplug.streams.StreamState` while exporting: state in and out as tensors.

    :meth:`get` returns what ``StreamState.get`` would, computed from tensors: the previous value
    (:attr:`prev`, graph inputs) where the stream continues, ``on_reset(current)`` where it restarts,
    and the previous -> current ego motion from the two poses (float64, as eager). A slot restarts
    where ``is_start`` or where the frame-index or time step breaks the state's own rules
    (``max_frame_step``, ``max_gap_s``); the scene-name rule is the caller's ``is_start``. Branch-free
    (``torch.where``), so it traces. :meth:`update` keeps the new value for the graph's outputs.

    With :attr:`prev` None (the probe that finds the state's structure) every slot restarts.
    """

    def __init__(self, state: StreamState, previous: _Previous) -> None:
        self.state = state
        self.previous = previous
        self.prev: list[Tensor] | None = None
        self.new: list[Tensor] | None = None

    def get(self, batch: Batch, current: Any) -> StreamRead:
        init = self.state.on_reset(current)
        cur_pose = batch.ego_to_global.to(torch.float64)
        size = cur_pose.shape[0]
        eye = torch.eye(4, dtype=torch.float64, device=cur_pose.device).expand(size, 4, 4)
        p = self.previous
        if self.prev is None or p.is_start is None:
            reset = torch.ones(size, dtype=torch.bool, device=cur_pose.device)
            return StreamRead(init, reset, eye.clone(), torch.zeros(size, dtype=torch.float64, device=cur_pose.device))
        reset = p.is_start.to(torch.bool)
        if self.state.max_frame_step is not None:
            step = batch.frame_index.to(torch.int64) - p.frame_index.to(torch.int64)
            reset = reset | (step < 1) | (step > self.state.max_frame_step)
        dt = batch.timestamp.to(torch.float64) - p.timestamp.to(torch.float64)
        if self.state.max_gap_s is not None:
            reset = reset | (dt <= 0) | (dt > self.state.max_gap_s)
        leaves = iter(self.prev)

        def pick(new: Tensor) -> Tensor:
            return torch.where(reset.view(-1, *[1] * (new.dim() - 1)), new, next(leaves).to(new.dtype))

        value = _map(pick, init)
        motion = torch.where(reset.view(-1, 1, 1), eye, relative_pose(p.ego_to_global.to(torch.float64), cur_pose))
        return StreamRead(value, reset, motion, torch.where(reset, torch.zeros_like(dt), dt))

    def update(self, batch: Batch, value: Any) -> None:
        self.new = _leaves(value)


def _traceable_forward(holder: nn.Module) -> Callable[..., Any] | None:
    """The branch-free forward ``holder`` runs while exporting: its own ``export_forward``, or None (its
    forward traces as it is)."""
    return getattr(holder, "export_forward", None)


def _stream_holders(model: nn.Module) -> list[tuple[str, nn.Module, str, StreamState]]:
    """``(qualified name, holder, attribute, state)`` of every StreamState in ``model`` (as :func:`find_streams`)."""
    out = []
    for name, sub in model.named_modules():
        for attr, value in list(vars(sub).items()):
            if isinstance(value, StreamState):
                out.append((f"{name}.{attr}" if name else attr, sub, attr, value))
    return out


def is_streaming(model: nn.Module) -> bool:
    """Whether ``model`` holds a :class:`~occplug.streams.StreamState` (its export is a stream step)."""
    return bool(_stream_holders(model))


@contextlib.contextmanager
def _explicit_streams(model: nn.Module) -> Iterator[list[tuple[str, ExplicitStream]]]:
    """Inside: every StreamState of ``model`` replaced by an :class:`ExplicitStream` (sharing one
    :class:`_Previous`), and every holder whose forward is not traceable running its equivalent."""
    holders = _stream_holders(model)
    previous = _Previous()
    streams = [(name, ExplicitStream(state, previous)) for name, _, _, state in holders]
    patched: list[nn.Module] = []
    try:
        for (_, holder, attr, _), (_, stream) in zip(holders, streams, strict=True):
            setattr(holder, attr, stream)
            forward = None if holder in patched else _traceable_forward(holder)
            if forward is not None:
                holder.forward = forward
                patched.append(holder)
        yield streams
    finally:
        for _, holder, attr, state in holders:
            setattr(holder, attr, state)
        for holder in patched:
            del holder.forward


class StreamingWrapper(nn.Module):
    """The exported function of a streaming model: one step, the state an explicit input and output.

    Forward: ``names`` (:func:`graph_inputs`), :data:`STREAM_INPUTS`, then the previous state tensors
    (``prev_state.<name>``) -> ``(class_ids, logits, *state)``: the new state tensors (``state.<name>``) in the
    same order. Built inside :func:`_explicit_streams` (``streams`` are its stand-ins).
    """

    def __init__(
        self,
        model: nn.Module,
        template: Batch,
        streams: list[ExplicitStream],
        sizes: list[int],
        names: Sequence[str] = INPUTS,
    ) -> None:
        super().__init__()
        self.model = model
        self.template = template
        self.streams = streams
        self.sizes = sizes
        self.names = tuple(names)

    def forward(self, *args: Tensor) -> tuple[Tensor, ...]:
        n, m = len(self.names), len(STREAM_INPUTS)
        ego, timestamp, frame_index, is_start, prev_ego, prev_timestamp, prev_frame_index = args[n : n + m]
        state = list(args[n + m :])
        previous = self.streams[0].previous
        previous.is_start, previous.ego_to_global = is_start, prev_ego
        previous.timestamp, previous.frame_index = prev_timestamp, prev_frame_index
        for stream, size in zip(self.streams, self.sizes, strict=True):
            stream.prev, state = state[:size], state[size:]
        batch = _batch_of(
            self.template, self.names, args[:n],
            ego_to_global=ego, timestamp=timestamp, frame_index=frame_index, is_sequence_start=is_start,
        )
        logits = occupancy_logits(self.model, self.model(batch))
        new = [t for stream in self.streams for t in (stream.new or [])]
        return (logits.argmax(dim=1), logits, *new)


def stream_inputs(batch: Batch, previous: Batch | None) -> tuple[Tensor, ...]:
    """The :data:`STREAM_INPUTS` of ``batch`` following ``previous`` (None: the first frame).

    ``is_start`` is the batch's ``is_sequence_start``, or no previous frame, or another scene than
    the previous frame's (strings are no graph input); the graph applies the time and frame rules.
    """
    size = batch.ego_to_global.shape[0]
    start = batch.is_sequence_start.to(torch.bool).clone()
    if previous is None:
        start[:] = True
        prev = (torch.eye(4, dtype=torch.float64).repeat(size, 1, 1), torch.zeros(size, dtype=torch.float64),
                torch.zeros(size, dtype=torch.int64))
    else:
        start |= torch.tensor([a != b for a, b in zip(batch.scene, previous.scene, strict=True)])
        prev = (previous.ego_to_global, previous.timestamp, previous.frame_index)
    pose, time_s, index = (batch.ego_to_global, batch.timestamp, batch.frame_index)
    return tuple(
        t.to(dtype).contiguous()
        for t, dtype in zip(
            (pose, time_s, index, start, *prev),
            (torch.float64, torch.float64, torch.int64, torch.bool, torch.float64, torch.float64, torch.int64),
            strict=True,
        )
    )


def example_inputs(model: nn.Module, batch: Batch) -> tuple[Tensor, ...]:
    """Every graph input for ``batch`` as a stream's first frame: :func:`inputs_of`; for a streaming model
    also :func:`stream_inputs` (``is_start``) and a zero state (runs the model once to find its shapes)."""
    with _graph(model, batch) as graph:
        return graph.args


@dataclasses.dataclass
class _Graph:
    """What is exported: the wrapper, example inputs and the inputs' and outputs' names."""

    wrapper: nn.Module
    args: tuple[Tensor, ...]
    input_names: list[str]
    output_names: list[str]
    state_names: list[str] = dataclasses.field(default_factory=list)
    initial_state: list[Tensor] = dataclasses.field(default_factory=list)

    @property
    def dynamic_shapes(self) -> tuple[tuple[dict[int, Any] | None, ...]] | None:
        """``torch.export``'s ``dynamic_shapes``: the point count of ``points`` (None without a point input)."""
        if "points" not in self.input_names:
            return None
        count = torch.export.Dim("points", min=2)
        # the wrappers take *args: one entry, the specs of all positional inputs
        return (tuple({1: count} if name == "points" else None for name in self.input_names),)


@contextlib.contextmanager
def _graph(model: nn.Module, template: Batch) -> Iterator[_Graph]:
    """The :class:`_Graph` of ``model`` on ``template``'s shapes, ready to trace inside (raises ExportError)."""
    check_exportable(model)
    inputs = graph_inputs(model)
    with export_ready(model), _explicit_streams(model) as named:
        if not named:
            wrapper = InferenceWrapper(model, template, inputs).eval()
            yield _Graph(wrapper, inputs_of(template, inputs), list(inputs), list(OUTPUTS))
            return
        streams = [s for _, s in named]
        with torch.no_grad(), _quiet():  # the probe: one restarting step gives each state's structure
            model(template)
        names, initial, sizes = [], [], []
        for (name, stream) in named:
            if stream.new is None:
                raise ExportError(f"export: model.{name.rsplit('.', 1)[0]} never stores its stream state")
            sizes.append(len(stream.new))
            names += [name if len(stream.new) == 1 else f"{name}.{i}" for i in range(len(stream.new))]
            initial += [torch.zeros_like(t) for t in stream.new]
            stream.new = None
        wrapper = StreamingWrapper(model, template, streams, sizes, inputs).eval()
        yield _Graph(
            wrapper, (*inputs_of(template, inputs), *stream_inputs(template, None), *initial),
            [*inputs, *STREAM_INPUTS, *(f"prev_state.{n}" for n in names)],
            [*OUTPUTS, *(f"state.{n}" for n in names)], names, initial,
        )


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
        ExportError: a model that encodes past frames (``input_history``), a stateful component keeping its state
            outside a :class:`~occplug.streams.StreamState`
            (the graph's state inputs and outputs are those of the stream states), or an inference
            component reading a batch field that is no graph input (e.g. LiDAR ``points``).
    """
    if getattr(model, "input_history", None):
        raise ExportError(
            f"model.input_history {list(model.input_history)}: the exported graph takes one frame's inputs; a model "
            "that encodes past frames cannot be exported"
        )
    holders = [holder for _, holder, _, _ in _stream_holders(model)]
    for name, sub in model.named_modules():
        if name and is_stateful(sub) and not set(sub.modules()).intersection(holders):
            raise ExportError(
                f"model.{name} ({type(sub).__name__}) is stateful but keeps its state outside an "
                "occplug.streams.StreamState; export takes a stream's state only through StreamState"
            )
    supervision = _supervision_modules(model)
    for name, sub in model.named_modules():
        extra = set(getattr(sub, "requires", ()) or ()) - _SUPPORTED_FIELDS
        if extra and id(sub) not in supervision:  # supervision is not part of inference
            raise ExportError(
                f"model.{name} ({type(sub).__name__}) reads batch field(s) {', '.join(sorted(extra))}; the exported "
                f"graph takes only {', '.join(INPUTS)} (and {', '.join(POINT_INPUTS)} for a model that reads LiDAR)"
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


# ---------------------------------------------------------------------------------------------- parity
def perturb(batch: Batch, seed: int) -> Batch:
    """``batch`` seen by another rig: perturbed intrinsics and extrinsics, and an image augmentation.

    Focal lengths scale by up to +-8 %, the principal point moves by up to 4 % of the image size,
    every camera (and the LiDAR, where the batch has one) turns by up to 2 degrees of yaw and moves by up to
    0.2 m, and the images are
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
    def turn(*shape: int) -> Tensor:  # (*shape, 4, 4): up to 2 degrees of yaw and 0.2 m
        yaw = math.radians(2.0) * u(*shape)
        out = torch.eye(4).repeat(*shape, 1, 1)
        out[..., 0, 0], out[..., 0, 1] = torch.cos(yaw), -torch.sin(yaw)
        out[..., 1, 0], out[..., 1, 1] = torch.sin(yaw), torch.cos(yaw)
        out[..., :3, 3] = 0.2 * u(*shape, 3)
        return out

    cam_to_ego = turn(b, n) @ batch.cam_to_ego.float()
    scale = 1 + 0.1 * u(b, n)
    aug = torch.eye(3).repeat(b, n, 1, 1)  # pixel u -> (w - 1) - u, then scale about the image centre
    aug[..., 0, 0], aug[..., 0, 2] = -scale, (w - 1) / 2 * (1 + scale)
    aug[..., 1, 1], aug[..., 1, 2] = scale, (h - 1) / 2 * (1 - scale)
    img_aug = aug @ batch.img_aug.float()
    lidar = {}
    if batch.lidar_to_ego is not None:  # the LiDAR turns and moves like a camera
        lidar["lidar_to_ego"] = turn(b).to(batch.lidar_to_ego.dtype) @ batch.lidar_to_ego
    return dataclasses.replace(
        batch, images=batch.images.flip(-1).contiguous(), intrinsics=k, cam_to_ego=cam_to_ego, img_aug=img_aug,
        **lidar,
    )


def report_path(out: Path) -> Path:
    """Where the parity report of artefact ``out`` goes: ``<out>.parity.json`` beside it."""
    out = Path(out)
    return out.with_name(out.name + ".parity.json")


def _report(
    fmt: str, frames: int, perturbed: int, voxels: int, max_diff: float, agree: int, eager_ms: list, exported_ms: list
) -> dict[str, Any]:
    """The parity report's common entries (see :func:`parity`)."""
    return {
        "format": fmt,
        "frames": frames,
        "frames_perturbed": perturbed,
        "voxels": voxels,
        "max_abs_logit_diff": max_diff,
        "class_agreement": agree / max(voxels, 1),
        "eager_latency_ms": statistics.median(eager_ms),
        "exported_latency_ms": statistics.median(exported_ms),
        "versions": _versions(fmt),
    }


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
        "versions"}``; a streaming model's (:func:`stream_parity`) also ``"stream"``.
    """
    if is_streaming(model):
        return stream_parity(model, exported, batches, fmt, repeats)
    model.eval()
    names = graph_inputs(model)
    frames = [f for i, batch in enumerate(batches) for f in (batch, perturb(batch, seed=i))]
    max_diff, agree, voxels = 0.0, 0, 0
    eager_ms: list[float] = []
    exported_ms: list[float] = []
    with torch.no_grad():
        for batch in frames[:1]:  # warm-up (first calls allocate, build plans)
            model.predict_occupancy(batch)
            exported(*inputs_of(batch, names))
        for batch in frames:
            args = inputs_of(batch, names)
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
    return _report(fmt, len(batches), len(frames) - len(batches), voxels, max_diff, agree, eager_ms, exported_ms)


def _eager_outputs(model: OccupancyModel, batch: Batch) -> tuple[Tensor, Tensor]:
    outputs = model(batch)
    logits = occupancy_logits(model, outputs)
    ids = model.occupancy_from(outputs) if hasattr(model, "occupancy_from") else logits.argmax(dim=1)
    return ids, logits


def _stored(states: Sequence[StreamState], stage: str) -> list[Tensor]:
    """The values ``states`` hold for ``stage``, as the graph's state tensors (slots stacked, leaves in order)."""
    out: list[Tensor] = []
    for state in states:
        store = state.state_dict().get(stage, {})
        per_slot = [_leaves(store[b]["value"]) for b in sorted(store)]
        out += [torch.stack(leaves) for leaves in zip(*per_slot, strict=True)]
    return out


def stream_parity(
    model: OccupancyModel,
    exported: Callable[..., tuple[Tensor, ...]],
    batches: Sequence[Batch],
    fmt: str,
    repeats: int = 3,
) -> dict[str, Any]:
    """:func:`parity` of a streaming model: ``batches`` run in order as a sequence, then again perturbed.

    The eager model keeps its state in its own :class:`~occplug.streams.StreamState` (the
    ``predict`` store, emptied before each sequence); the exported one gets the previous frame's
    state outputs back as inputs (the zero state and ``is_start`` at the first frame, see
    :func:`stream_inputs`). Every frame compares logits, classes and the new state. Each timed
    repeat of the eager step first restores the state it started from.

    Returns:
        :func:`parity`'s keys, plus ``"stream": {"states" (the state tensors' names), "sequence_starts"
        (frames fed with ``is_start``), "max_abs_state_diff"}``.
    """
    model.eval()
    states = [state for *_, state in _stream_holders(model)]
    with _graph(model, batches[0]) as graph:  # the state tensors' names and zero initial values
        names, initial = list(graph.state_names), list(graph.initial_state)
    saved = [(state.stage, state.state_dict()) for state in states]
    sequences = [list(batches), [perturb(batch, seed=i) for i, batch in enumerate(batches)]]
    max_diff, state_diff, agree, voxels, starts = 0.0, 0.0, 0, 0, 0
    eager_ms: list[float] = []
    exported_ms: list[float] = []
    inputs = graph_inputs(model)
    start_at = len(inputs) + STREAM_INPUTS.index("is_start")
    try:
        set_stream_stage(model, "predict")
        with torch.no_grad():
            _eager_outputs(model, batches[0])  # warm-up (first calls allocate, build plans)
            exported(*inputs_of(batches[0], inputs), *stream_inputs(batches[0], None), *initial)
            for sequence in sequences:
                for state in states:
                    state.clear("predict")
                carried, previous = list(initial), None
                for batch in sequence:
                    args = (*inputs_of(batch, inputs), *stream_inputs(batch, previous), *carried)
                    starts += int(args[start_at].sum())
                    before = [state.state_dict() for state in states]
                    eager_t, got_t = [], []
                    for r in range(max(1, repeats)):
                        if r:  # the same step again, from the same state
                            for state, entries in zip(states, before, strict=True):
                                state.load_state_dict(entries)
                        t0 = time.perf_counter()
                        eager_ids, eager_logits = _eager_outputs(model, batch)
                        t1 = time.perf_counter()
                        got = exported(*args)
                        t2 = time.perf_counter()
                        eager_t.append(t1 - t0)
                        got_t.append(t2 - t1)
                    eager_ms.append(min(eager_t) * 1e3)
                    exported_ms.append(min(got_t) * 1e3)
                    ids, logits, *carried = got
                    max_diff = max(max_diff, float((logits.float() - eager_logits.float()).abs().max()))
                    agree += int((ids.long() == eager_ids.long()).sum())
                    voxels += int(eager_ids.numel())
                    for mine, theirs in zip(carried, _stored(states, "predict"), strict=True):
                        state_diff = max(state_diff, float((mine.float() - theirs.float()).abs().max()))
                    previous = batch
    finally:
        for state, (stage, entries) in zip(states, saved, strict=True):
            state.load_state_dict(entries)
            state.set_stage(stage)
    report = _report(fmt, len(batches), len(batches), voxels, max_diff, agree, eager_ms, exported_ms)
    report["stream"] = {"states": names, "sequence_starts": starts, "max_abs_state_diff": state_diff}
    return report


#: What the baseline reaches (README, Export); ``occplug export`` fails a report outside them.
MIN_CLASS_AGREEMENT = 0.9999
MAX_LOGIT_DIFF = 1e-4


def passes(report: dict[str, Any]) -> bool:
    """Whether a :func:`parity` report is within :data:`MIN_CLASS_AGREEMENT` and :data:`MAX_LOGIT_DIFF`."""
    return report["class_agreement"] >= MIN_CLASS_AGREEMENT and report["max_abs_logit_diff"] <= MAX_LOGIT_DIFF


def one_line(report: dict[str, Any]) -> str:
    """The report as the one line ``occplug export`` prints."""
    versions = " ".join(f"{k}={v}" for k, v in report["versions"].items())
    stream = report.get("stream")
    order = (
        f" (in order, state fed back, {stream['sequence_starts']} stream starts, max |state diff| "
        f"{stream['max_abs_state_diff']:.3g})"
        if stream else ""
    )
    return (
        f"parity {report['format']}: {report['frames']} frames + {report['frames_perturbed']} perturbed{order}, "
        f"classes agree on {100 * report['class_agreement']:.4f} % of {report['voxels']} voxels, "
        f"max |logit diff| {report['max_abs_logit_diff']:.3g}, latency eager {report['eager_latency_ms']:.1f} ms "
        f"vs exported {report['exported_latency_ms']:.1f} ms ({versions})"
    )


def export_checkpoint(ckpt: Path, fmt: str, out: Path, samples: int = 4) -> dict[str, Any]:
    """``occplug export``: rebuild the model from ``ckpt`` alone, export it to ``out``, check parity.

    The first ``samples`` frames of the checkpoint's validation split (then of its training split,
    where the validation split is shorter), batch size 1, are the parity frames; the first fixes the
    exported shapes (batch size 1, camera count, image size). A streaming model's frames run in that
    order, as a sequence (:func:`stream_parity`). Writes the report (:func:`parity`, plus
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
