"""SavedTensorProfile charges the tensors autograd saves to the module running when they are saved."""

from __future__ import annotations

import torch
from torch import nn

from occplug.run.memory import SavedTensorProfile


class Net(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.first = nn.Linear(4, 8)
        self.act = nn.ReLU()
        self.second = nn.Linear(8, 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.second(self.act(self.first(x))) * 3.0  # a multiply by a constant saves nothing


def test_saved_bytes_per_module_are_the_hand_counted_activations() -> None:
    model = Net()
    x = torch.randn(5, 4)
    with SavedTensorProfile(model) as profile:
        out = model(x)
    out.sum().backward()  # the saved tensors still serve the backward pass
    # first: its input (5 x 4 float32; the weight is a parameter, not counted); act: its output (5 x 8), which
    # second saves again as its input: the same storage, counted once, where it was first saved
    assert profile.saved["first"] == 5 * 4 * 4
    assert profile.saved["act"] == 5 * 8 * 4
    assert profile.saved.get("second", 0) == 0
    assert profile.total == (5 * 4 + 5 * 8) * 4
    assert profile.by_prefix(1) == {"act": 160, "first": 80}
    rows = profile.table(depth=1).splitlines()
    assert rows[2:] == ["| act | 0 | 66.7 % |", "| first | 0 | 33.3 % |", "| total | 0 | 100 % |"]  # largest first
    assert model.first.weight.grad is not None


def test_hooks_are_removed_and_nothing_is_counted_outside() -> None:
    model = Net()
    with SavedTensorProfile(model) as profile:
        pass
    model(torch.randn(3, 4)).sum().backward()
    assert profile.total == 0
    assert not model.first._forward_hooks and not model.first._forward_pre_hooks


def test_peak_rss_counts_memory_touched_after_its_reset():
    import sys

    import pytest

    from occplug.run.memory import peak_rss, reset_peak_rss

    if not sys.platform.startswith("linux"):
        pytest.skip("the peak is reset through /proc/self/clear_refs (Linux)")
    import mmap

    reset_peak_rss()
    before = peak_rss()
    size = 64 * 2**20
    block = mmap.mmap(-1, size)  # fresh pages from the kernel (a freed tensor's pages may be reused instead)
    for offset in range(0, size, mmap.PAGESIZE):
        block[offset] = 1  # touched: resident
    assert peak_rss() - before >= 48 * 2**20
    block.close()
