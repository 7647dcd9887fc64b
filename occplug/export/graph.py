"""What the exported graph is: its inputs and outputs, the wrappers traced, and what makes a model exportable.

The graph's inputs and outputs (:data:`INPUTS`, :data:`POINT_INPUTS`, :data:`STREAM_INPUTS`, :data:`OUTPUTS`), the
functions traced (:class:`InferenceWrapper`, one frame; :class:`StreamingWrapper`, one step of a stream, each
:class:`~occplug.streams.StreamState` replaced by an :class:`ExplicitStream`), a batch's values of those inputs
(:func:`inputs_of`, :func:`stream_inputs`, :func:`example_inputs`), the splat's traceable path
(:func:`export_ready`) and the one-line refusals of a model the graph cannot represent (:func:`check_exportable`).
Why the graph is cut this way is in the :mod:`occplug.export` docstring.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import logging
import warnings
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import torch
from torch import Tensor, nn

from occplug.data.frame import Batch
from occplug.errors import UserError
from occplug.geometry import relative_pose
from occplug.ops.splat import FrustumSplatter
from occplug.streams import StreamRead, StreamState, is_stateful, tree_leaves, tree_map

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

        value = tree_map(pick, init)
        motion = torch.where(reset.view(-1, 1, 1), eye, relative_pose(p.ego_to_global.to(torch.float64), cur_pose))
        return StreamRead(value, reset, motion, torch.where(reset, torch.zeros_like(dt), dt))

    def update(self, batch: Batch, value: Any) -> None:
        self.new = tree_leaves(value)


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

    The ``fast`` path's plan cache is keyed by a host-side hash of the calibration (see the
    :mod:`occplug.export` docstring); the reference path computes the same frustum geometry from the input tensors.
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
