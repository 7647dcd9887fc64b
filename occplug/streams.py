"""Stream state: what a stateful component carries from one frame of a sequence to the next.

A streaming component (a warped feature volume, an instance bank) keeps, per batch slot, what it
computed for the previous frame of that slot and reads it back at the next frame.
:class:`StreamState` does the bookkeeping once for every component:

* **per batch slot**, keyed by the slot's sequence identity: each stored entry remembers the
  frame it was computed for (``scene``, ``frame_index``, ``timestamp``, ``ego_to_global``);
* **reset** where the new frame does not continue the stored one: ``batch.is_sequence_start``,
  another scene, a frame-index step other than ``1..max_frame_step``, or a time step outside
  ``(0, max_gap_s]``; a reset puts in ``on_reset(current)`` (zeros by default; DuOcc puts in the
  current frame's features);
* **random cuts in training** (``train_cut_prob``, off by default): in a training step (the ``train``
  store, gradients on) a continuing slot is reset with that probability, so a model that leans on its
  history also learns to predict from the current frame alone. Evaluation and any ``no_grad`` call
  (prediction outside Lightning too) never cut;
* **any nested structure** of tensors (dicts, lists, tuples) with the batch on dim 0;
* **detached** when stored, so no gradient flows across frames;
* **one store per stage** (``train``, ``val``, ``test``, ``predict``): the sanity check and a
  mid-epoch validation never overwrite the training state. :class:`StreamStages` (added by the
  model through ``configure_callbacks``) tells every state the current stage;
* **not checkpointed** unless ``persistent=True``.

Components that hold a state declare ``stateful = True`` (a class attribute; absent means False);
:func:`check_streaming` rejects a stateful model whose data is not read sequentially.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor, nn

from occplug.geometry import relative_pose

__all__ = ["STAGES", "StreamRead", "StreamStages", "StreamState", "check_streaming", "find_streams",
           "is_stateful", "set_stream_stage", "tree_leaves", "tree_map", "zeros_like"]

#: The stores of a :class:`StreamState`, one per Lightning loop.
STAGES = ("train", "val", "test", "predict")


def tree_map(fn: Callable[..., Any], tree: Any, *others: Any) -> Any:
    """Apply ``fn`` to the tensor leaves of nested dicts / lists / tuples (``others`` share the structure)."""
    if isinstance(tree, Tensor):
        return fn(tree, *others)
    if isinstance(tree, dict):
        if any(not isinstance(o, dict) or o.keys() != tree.keys() for o in others):
            raise ValueError("StreamState: the stored and the new structure differ (dict keys)")
        return {k: tree_map(fn, v, *(o[k] for o in others)) for k, v in tree.items()}
    if isinstance(tree, (list, tuple)):
        if any(not isinstance(o, (list, tuple)) or len(o) != len(tree) for o in others):
            raise ValueError("StreamState: the stored and the new structure differ (sequence length)")
        items = [tree_map(fn, v, *(o[i] for o in others)) for i, v in enumerate(tree)]
        if isinstance(tree, tuple) and hasattr(tree, "_fields"):  # a namedtuple
            return type(tree)(*items)
        return type(tree)(items)
    if tree is None:
        return None
    raise TypeError(f"StreamState holds tensors in dicts, lists and tuples, not {type(tree).__name__}")


def tree_leaves(tree: Any) -> list[Tensor]:
    out: list[Tensor] = []
    tree_map(lambda t: out.append(t), tree)
    return out


def zeros_like(current: Any) -> Any:
    """The default reset: zeros shaped like ``current`` (any nested structure)."""
    return tree_map(torch.zeros_like, current)


@dataclass
class _Entry:
    value: Any  # one slot's slice of the structure, detached
    scene: str
    frame_index: int
    timestamp: float
    ego_to_global: Tensor  # (4, 4) float64


@dataclass
class StreamRead:
    """What :meth:`StreamState.get` returns for a batch of ``B`` frames.

    Attributes:
        value: the nested structure, every leaf ``(B, ...)``: the stored previous value of each
            continuing slot, ``on_reset(current)`` of each reset slot. Stored values are in the
            **previous** frame's ego frame (warp them with ``prev_to_current``).
        reset: ``(B,)`` bool, the slots that were reset.
        prev_to_current: ``(B, 4, 4)`` float64 pose mapping the stored frame's ego frame into the
            current ego frame (``T_{g->e}^t T_{e->g}^{t-1}``, DuOcc Eq. 1); identity where reset.
        dt: ``(B,)`` float64 seconds since the stored frame; 0 where reset.
    """

    value: Any
    reset: Tensor
    prev_to_current: Tensor
    dt: Tensor


class StreamState:
    """Per-slot, per-stage state of a streaming component (see the module docstring).

    Args:
        on_reset: ``on_reset(current) -> initial value`` for the slots that start a stream, given
            the whole batch's ``current`` structure (leaves ``(B, ...)``); the default is
            :func:`zeros_like`. Its result must have the structure and shapes of what
            :meth:`update` stores.
        max_gap_s: reset when the time since the stored frame is not in ``(0, max_gap_s]``
            seconds; None skips the time check (DuOcc: 2 s).
        max_frame_step: reset when ``frame_index`` does not advance by ``1..max_frame_step``; None
            skips the check.
        persistent: store the state in checkpoints (:class:`StreamStages`); default off.
        train_cut_prob: probability, in ``[0, 1)``, of resetting a continuing slot in a training step
            (``train`` stage with gradients on). Drawn from torch's global generator: a seeded run
            repeats, and draws other random numbers after the first cut than a run without cuts.
            0 never cuts.
        allow_backward: also continue when time runs backwards by at most ``max_gap_s`` (the time since
            the stored frame in ``[-max_gap_s, 0)``; with ``max_frame_step=None``, since a step back
            fails the frame check). Default off: time must advance.

    Attributes:
        stage: the store :meth:`get` and :meth:`update` use (set by :func:`set_stream_stage`).
    """

    def __init__(self, on_reset: Callable[[Any], Any] | None = None, max_gap_s: float | None = 2.0,
                 max_frame_step: int | None = 1, persistent: bool = False, train_cut_prob: float = 0.0,
                 allow_backward: bool = False) -> None:
        if max_gap_s is not None and max_gap_s <= 0:
            raise ValueError(f"StreamState max_gap_s must be positive or None, got {max_gap_s}")
        if max_frame_step is not None and max_frame_step < 1:
            raise ValueError(f"StreamState max_frame_step must be >= 1 or None, got {max_frame_step}")
        if not 0.0 <= train_cut_prob < 1.0:
            raise ValueError(f"StreamState train_cut_prob must be in [0, 1), got {train_cut_prob}")
        self.on_reset = on_reset or zeros_like
        self.max_gap_s = max_gap_s
        self.max_frame_step = max_frame_step
        self.persistent = bool(persistent)
        self.train_cut_prob = float(train_cut_prob)
        self.allow_backward = bool(allow_backward)
        self.stage = "train"
        self._stores: dict[str, dict[int, _Entry]] = {}

    # ------------------------------------------------------------------ bookkeeping
    def set_stage(self, stage: str) -> None:
        """Switch to ``stage``'s store (one of :data:`STAGES`)."""
        if stage not in STAGES:
            raise ValueError(f"StreamState stage must be one of {', '.join(STAGES)}, got {stage!r}")
        self.stage = stage

    def clear(self, stage: str | None = None) -> None:
        """Forget the entries of ``stage`` (default: every stage)."""
        if stage is None:
            self._stores.clear()
        else:
            self._stores.pop(stage, None)

    def slots(self, stage: str | None = None) -> dict[int, tuple[str, int, float]]:
        """``{slot: (scene, frame_index, timestamp)}`` of the frames stored for ``stage`` (default: current)."""
        store = self._stores.get(self.stage if stage is None else stage, {})
        return {b: (e.scene, e.frame_index, e.timestamp) for b, e in sorted(store.items())}

    def _continues(self, entry: _Entry | None, batch: Any, b: int) -> bool:
        if entry is None or bool(batch.is_sequence_start[b]) or batch.scene[b] != entry.scene:
            return False
        step = int(batch.frame_index[b]) - entry.frame_index
        if self.max_frame_step is not None and not 1 <= step <= self.max_frame_step:
            return False
        dt = float(batch.timestamp[b]) - entry.timestamp
        if self.allow_backward:
            dt = abs(dt)
        return self.max_gap_s is None or 0.0 < dt <= self.max_gap_s

    # ------------------------------------------------------------------ read / write
    def get(self, batch: Any, current: Any) -> StreamRead:
        """The state of every slot of ``batch`` (a :class:`~occplug.data.Batch`), reset where needed.

        Args:
            batch: the current frames (``scene``, ``frame_index``, ``timestamp``,
                ``is_sequence_start``, ``ego_to_global`` are read).
            current: this step's structure (leaves ``(B, ...)``), handed to ``on_reset``.
        """
        size = len(batch.scene)
        store = self._stores.get(self.stage, {})
        init = self.on_reset(current)
        init_leaves = tree_leaves(init)
        ref = init_leaves[0] if init_leaves else None
        cont = []
        for b in range(size):
            entry = store.get(b)
            ok = self._continues(entry, batch, b)
            if ok and entry is not None:  # a stored shape that no longer fits (another resolution) restarts
                ok = all(s.shape == i.shape[1:] for s, i in zip(tree_leaves(entry.value), init_leaves, strict=True))
            cont.append(ok)
        if self.train_cut_prob > 0.0 and self.stage == "train" and torch.is_grad_enabled():
            cut = (torch.rand(size) < self.train_cut_prob).tolist()
            cont = [c and not k for c, k in zip(cont, cut, strict=True)]
        cur_pose = batch.ego_to_global.to(torch.float64)
        device = cur_pose.device
        reset = torch.tensor([not c for c in cont], dtype=torch.bool, device=ref.device if ref is not None else device)
        motion = torch.eye(4, dtype=torch.float64, device=device).repeat(size, 1, 1)
        dt = torch.zeros(size, dtype=torch.float64, device=device)
        if not any(cont):
            return StreamRead(init, reset, motion, dt)
        for b, c in enumerate(cont):
            if c:
                entry = store[b]
                motion[b] = relative_pose(entry.ego_to_global.to(device), cur_pose[b])
                dt[b] = float(batch.timestamp[b]) - entry.timestamp

        def pick(new: Tensor, *stored: Any) -> Tensor:
            rows = [stored[b].to(device=new.device, dtype=new.dtype) if c else new[b] for b, c in enumerate(cont)]
            return torch.stack(rows)

        stored_values = [store[b].value if c else _slice(init, b) for b, c in enumerate(cont)]
        value = tree_map(pick, init, *stored_values)
        return StreamRead(value, reset, motion, dt)

    def update(self, batch: Any, value: Any) -> None:
        """Store ``value`` (leaves ``(B, ...)``) for every slot of ``batch``, detached."""
        store = self._stores.setdefault(self.stage, {})
        poses = batch.ego_to_global.detach().to(torch.float64)
        for b in range(len(batch.scene)):
            store[b] = _Entry(
                value=tree_map(lambda t, b=b: t[b].detach(), value),
                scene=str(batch.scene[b]),
                frame_index=int(batch.frame_index[b]),
                timestamp=float(batch.timestamp[b]),
                ego_to_global=poses[b],
            )

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Every stage's entries as plain data (loadable with ``weights_only=True``)."""
        return {
            stage: {
                b: {"value": e.value, "scene": e.scene, "frame_index": e.frame_index, "timestamp": e.timestamp,
                    "ego_to_global": e.ego_to_global}
                for b, e in store.items()
            }
            for stage, store in self._stores.items()
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Replace every stage's entries with those of :meth:`state_dict`."""
        self._stores = {stage: {int(b): _Entry(**e) for b, e in store.items()} for stage, store in state.items()}


def _slice(tree: Any, b: int) -> Any:
    """Slot ``b`` of a batched structure."""
    return tree_map(lambda t: t[b], tree)


# ---------------------------------------------------------------------------------------------- model level


def find_streams(module: nn.Module) -> Iterator[tuple[str, StreamState]]:
    """``(qualified name, state)`` of every :class:`StreamState` held as an attribute of ``module``'s submodules."""
    for name, sub in module.named_modules():
        for attr, value in vars(sub).items():
            if isinstance(value, StreamState):
                yield (f"{name}.{attr}" if name else attr), value


def set_stream_stage(module: nn.Module, stage: str) -> None:
    """Point every :class:`StreamState` inside ``module`` at ``stage``'s store."""
    for _, state in find_streams(module):
        state.set_stage(stage)


def is_stateful(module: nn.Module) -> bool:
    """Whether a component declares ``stateful = True``."""
    return bool(getattr(module, "stateful", False))


def check_streaming(model: nn.Module, datamodule: Any) -> None:
    """Raise one line when a stateful model is given data that is not read sequentially.

    Raises:
        ValueError: naming ``data.sequential`` and the first stateful component.
    """
    holders = {name.rsplit(".", 1)[0] if "." in name else "" for name, _ in find_streams(model)}
    stateful = [name for name, sub in model.named_modules() if name and (is_stateful(sub) or name in holders)]
    if stateful and not getattr(datamodule, "sequential", False):
        first = stateful[0]
        raise ValueError(
            f"data.sequential: model.{first} ({type(model.get_submodule(first)).__name__}) is stateful (it carries "
            "features from frame to frame) and needs data.sequential: true"
        )


class _StreamStagesHooks:
    """Tells every :class:`StreamState` of the model which loop runs, and checkpoints the persistent ones.

    Each batch selects its loop's store (so a validation inside an epoch leaves the training state
    alone); an evaluation loop's store is emptied when the loop starts and ends. States created
    with ``persistent=True`` are saved under ``checkpoint["stream_states"]`` and restored.

    A Lightning ``Callback`` (``StreamStages`` is this class and ``lightning.Callback``, built on first use by the
    module's ``__getattr__``, so importing :mod:`occplug.streams` imports no Lightning).
    """

    KEY = "stream_states"

    def _stage(self, pl_module: nn.Module, stage: str) -> None:
        set_stream_stage(pl_module, stage)

    def _clear(self, pl_module: nn.Module, stage: str) -> None:
        for _, state in find_streams(pl_module):
            state.clear(stage)

    def on_train_batch_start(self, trainer: Any, pl_module: nn.Module, batch: Any, batch_idx: int) -> None:
        self._stage(pl_module, "train")

    def on_validation_batch_start(self, trainer: Any, pl_module: nn.Module, batch: Any, batch_idx: int,
                                  dataloader_idx: int = 0) -> None:
        self._stage(pl_module, "val")

    def on_test_batch_start(self, trainer: Any, pl_module: nn.Module, batch: Any, batch_idx: int,
                            dataloader_idx: int = 0) -> None:
        self._stage(pl_module, "test")

    def on_predict_batch_start(self, trainer: Any, pl_module: nn.Module, batch: Any, batch_idx: int,
                               dataloader_idx: int = 0) -> None:
        self._stage(pl_module, "predict")

    def on_validation_epoch_start(self, trainer: Any, pl_module: nn.Module) -> None:
        self._clear(pl_module, "val")

    def on_validation_epoch_end(self, trainer: Any, pl_module: nn.Module) -> None:
        self._clear(pl_module, "val")

    def on_test_epoch_start(self, trainer: Any, pl_module: nn.Module) -> None:
        self._clear(pl_module, "test")

    def on_test_epoch_end(self, trainer: Any, pl_module: nn.Module) -> None:
        self._clear(pl_module, "test")

    def on_predict_epoch_start(self, trainer: Any, pl_module: nn.Module) -> None:
        self._clear(pl_module, "predict")

    def on_predict_epoch_end(self, trainer: Any, pl_module: nn.Module) -> None:
        self._clear(pl_module, "predict")

    def on_save_checkpoint(self, trainer: Any, pl_module: nn.Module, checkpoint: dict[str, Any]) -> None:
        saved = {name: state.state_dict() for name, state in find_streams(pl_module) if state.persistent}
        if saved:
            checkpoint[self.KEY] = saved

    def on_load_checkpoint(self, trainer: Any, pl_module: nn.Module, checkpoint: dict[str, Any]) -> None:
        saved = checkpoint.get(self.KEY) or {}
        for name, state in find_streams(pl_module):
            if state.persistent and name in saved:
                state.load_state_dict(saved[name])


if TYPE_CHECKING:  # the class __getattr__ builds, for type checkers
    import lightning as L

    class StreamStages(_StreamStagesHooks, L.Callback): ...


def __getattr__(name: str) -> Any:
    """``StreamStages``, the Lightning ``Callback`` of :class:`_StreamStagesHooks`: built (and Lightning imported) on
    first use, then a plain module attribute (so it pickles and compares as one class)."""
    if name == "StreamStages":
        import lightning as L

        cls = type(
            "StreamStages",
            (_StreamStagesHooks, L.Callback),
            {"__module__": __name__, "__qualname__": "StreamStages", "__doc__": _StreamStagesHooks.__doc__},
        )
        globals()["StreamStages"] = cls
        return cls
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
