"""Where a training step's memory goes: the tensors autograd saves for the backward pass, per module.

A training step's peak is mostly the activations kept for the backward pass. :class:`SavedTensorProfile` counts
them: while it is active, every tensor autograd saves (other than the model's parameters and buffers) is charged to
the innermost module whose ``forward`` is running (``torch.autograd.graph.saved_tensors_hooks`` and module forward
hooks), each storage once (a view of a tensor already counted adds nothing). Use it around one forward + loss::

    with SavedTensorProfile(model) as profile:
        loss = model.training_step(batch, 0)
    print(profile.table(depth=3))
    loss.backward()

Method-free: any ``nn.Module`` tree. It measures what is *saved*, not what is allocated and freed inside a
forward (the CPU's peak resident set or CUDA's peak allocation, printed beside it by the callers, includes those).
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

__all__ = ["SavedTensorProfile", "peak_rss", "reset_peak_rss"]


class SavedTensorProfile:
    """Bytes autograd saves for backward while active, charged to the innermost running module.

    Attributes:
        saved: module name (``""`` for code outside any module's forward) -> bytes saved there.
        count: module name -> number of distinct storages saved there.
    """

    def __init__(self, model: nn.Module) -> None:
        self.model = model
        self.saved: dict[str, int] = defaultdict(int)
        self.count: dict[str, int] = defaultdict(int)
        self._stack: list[str] = []
        self._seen: set[tuple[Any, ...]] = set()
        self._handles: list[Any] = []
        self._hooks: Any = None

    def _pack(self, tensor: Tensor) -> Tensor:
        if isinstance(tensor, Tensor) and tensor.device.type != "meta":
            storage = tensor.untyped_storage()
            key = (tensor.device.type, storage.data_ptr(), storage.nbytes())
            if key not in self._seen:  # parameters and buffers (and views of them) are in _seen from the start
                self._seen.add(key)
                where = self._stack[-1] if self._stack else ""
                self.saved[where] += storage.nbytes()
                self.count[where] += 1
        return tensor

    def __enter__(self) -> SavedTensorProfile:
        for tensor in [*self.model.parameters(), *self.model.buffers()]:  # weights are not activations
            storage = tensor.untyped_storage()
            self._seen.add((tensor.device.type, storage.data_ptr(), storage.nbytes()))

        def enter(name: str) -> Any:
            def hook(module: nn.Module, args: Any) -> None:
                self._stack.append(name)

            return hook

        def leave(module: nn.Module, args: Any, output: Any) -> None:  # returns None: the output stays
            self._stack.pop()

        for name, module in self.model.named_modules():
            self._handles.append(module.register_forward_pre_hook(enter(name)))
            self._handles.append(module.register_forward_hook(leave, always_call=True))
        self._hooks = torch.autograd.graph.saved_tensors_hooks(self._pack, lambda t: t)
        self._hooks.__enter__()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._hooks.__exit__(*exc)
        for handle in self._handles:
            handle.remove()
        self._handles.clear()
        self._seen.clear()

    @property
    def total(self) -> int:
        """All bytes saved while active."""
        return sum(self.saved.values())

    def by_prefix(self, depth: int) -> dict[str, int]:
        """Bytes per module name cut to its first ``depth`` dotted parts, largest first."""
        out: dict[str, int] = defaultdict(int)
        for name, nbytes in self.saved.items():
            out[".".join(name.split(".")[:depth]) if name else "(outside any module)"] += nbytes
        return dict(sorted(out.items(), key=lambda kv: -kv[1]))

    def table(self, depth: int = 3, top: int = 15) -> str:
        """A Markdown table of the ``top`` largest prefixes at ``depth``: MiB and share of the total."""
        total = max(self.total, 1)
        lines = ["| module | saved for backward (MiB) | share |", "|---|--:|--:|"]
        for name, nbytes in list(self.by_prefix(depth).items())[:top]:
            lines.append(f"| {name} | {nbytes / 2**20:,.0f} | {100.0 * nbytes / total:.1f} % |")
        lines.append(f"| total | {self.total / 2**20:,.0f} | 100 % |")
        return "\n".join(lines)


def reset_peak_rss() -> None:
    """Start a new peak: Linux's ``VmHWM`` is set to the current resident set (``/proc/self/clear_refs``); a no-op
    elsewhere, where :func:`peak_rss` then reports the process's lifetime peak."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def peak_rss() -> int:
    """Bytes: this process's peak resident set since the last :func:`reset_peak_rss` (Linux ``VmHWM``), else its
    lifetime peak (``ru_maxrss``)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    import resource  # Unix only: imported where it is needed

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
