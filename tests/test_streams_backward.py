"""StreamState(allow_backward=True): a slot whose time steps back by at most max_gap_s continues (DuOcc's public
code keeps its history for 0 < |dt| <= 2 s)."""

from __future__ import annotations

import torch

from occplug.streams import StreamState
from occplug.testing import hand_batch


def _frames(times, indices, starts=None):
    b = len(times)
    return hand_batch(
        b,
        scene=["a"] * b,
        frame_index=torch.tensor(indices),
        timestamp=torch.tensor(times, dtype=torch.float64),
        is_sequence_start=torch.tensor([False] * b if starts is None else starts),
    )


def test_allow_backward_keeps_a_step_back_within_the_gap_and_nothing_else_changes():
    first = _frames([10.0] * 6, [20] * 6)
    # dt per slot: +0.5, -0.5, -2.0, -2.5, 0, -1.0 with a sequence start
    nxt = _frames([10.5, 9.5, 8.0, 7.5, 10.0, 9.0], [21, 19, 16, 15, 20, 18], starts=[False] * 5 + [True])
    forward = StreamState(max_gap_s=2.0, max_frame_step=None)
    both = StreamState(max_gap_s=2.0, max_frame_step=None, allow_backward=True)
    for state in (forward, both):
        state.update(first, torch.arange(6.0))
    assert forward.get(nxt, torch.zeros(6)).reset.tolist() == [False, True, True, True, True, True]
    read = both.get(nxt, torch.zeros(6))
    assert read.reset.tolist() == [False, False, False, True, True, True]
    assert read.value.tolist() == [0.0, 1.0, 2.0, 0.0, 0.0, 0.0] and read.dt.tolist() == [0.5, -0.5, -2.0, 0, 0, 0]
    # with the frame check (default max_frame_step=1) a step back in frames still restarts
    framed = StreamState(max_gap_s=2.0, allow_backward=True)
    framed.update(first, torch.arange(6.0))
    assert framed.get(nxt, torch.zeros(6)).reset.tolist() == [False, True, True, True, True, True]
