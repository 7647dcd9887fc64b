"""Callback ``ema``: an exponential moving average of the model's weights, for evaluation, checkpoints and export.

Any model may want it (DuOcc's public code evaluates its EMA weights), so it lives in the core, method-free::

    callbacks:
      ema: {type: ema, decay: 0.999, ramp_steps: 2000}

After each optimiser step ``n`` (counted from 1 over the updates) the average ``e`` follows the weights ``w``:
``e_1 = w_1`` and ``e_n = d_n e_{n-1} + (1 - d_n) w_n`` with ``d_n = decay (1 - exp(-n / ramp_steps))``
(``d_n = decay`` when ``ramp_steps`` is 0; the ramp lets the average follow the fast early weights, as the
YOLOX-style EMA of DuOcc's code does).

Lightning's :class:`~lightning.pytorch.callbacks.WeightAveraging` does the rest: validation and testing during
``fit`` run on the average (swapped in and out), training ends with the average in the model, and every checkpoint
saved during ``fit`` holds the average as its ``state_dict`` (so ``occplug validate``, ``export``, ``predict`` and a
later phase's ``init_from`` read the EMA weights) and the raw weights under ``current_model_state``, with the
average's counter under ``averaging_state``: ``--resume`` continues both.
"""

from __future__ import annotations

import math
from typing import Annotated

from lightning.pytorch.callbacks import WeightAveraging
from torch import Tensor

from occplug.constraints import NonNegative, Positive, Range

__all__ = ["EMAWeights"]


class EMAWeights(WeightAveraging):
    """Exponential moving average of the weights (module docstring).

    Args:
        decay: ``d`` in ``[0, 1)``; 0 keeps the latest weights.
        ramp_steps: the ramp's time constant in updates (0: no ramp).
        every_n_steps: update after every n-th optimiser step.
        start_step: the first optimiser step (zero-based) that updates the average.
        buffers: average the buffers too (batch-norm statistics); else they are the latest.
    """

    def __init__(
        self,
        decay: Annotated[float, Range(low=0.0, high=1.0, high_open=True)] = 0.999,
        ramp_steps: Annotated[float, NonNegative] = 0.0,
        every_n_steps: Annotated[int, Positive] = 1,
        start_step: Annotated[int, NonNegative] = 0,
        buffers: bool = True,
    ) -> None:
        if not 0.0 <= decay < 1.0:
            raise ValueError(f"callbacks: ema decay must lie in [0, 1), got {decay}")
        if ramp_steps < 0 or every_n_steps < 1 or start_step < 0:
            raise ValueError("callbacks: ema ramp_steps and start_step must be >= 0, every_n_steps >= 1")
        self.decay, self.ramp_steps = float(decay), float(ramp_steps)
        self.every_n_steps, self.start_step = int(every_n_steps), int(start_step)
        super().__init__(use_buffers=buffers, avg_fn=self._average)

    def decay_at(self, n: int) -> float:
        """``d_n`` of the ``n``-th update (1-based)."""
        if self.ramp_steps == 0:
            return self.decay
        return self.decay * (1.0 - math.exp(-n / self.ramp_steps))

    def _average(self, averaged: Tensor, current: Tensor, num_averaged: Tensor | int) -> Tensor:
        """One update of ``averaged`` towards ``current`` (``num_averaged`` earlier updates; the first copies)."""
        d = self.decay_at(int(num_averaged) + 1)
        return averaged * d + current * (1.0 - d)

    def should_update(self, step_idx: int | None = None, epoch_idx: int | None = None) -> bool:
        """After the optimiser steps ``start_step, start_step + every_n_steps, ...`` (never at an epoch's end)."""
        if step_idx is None:
            return False
        return step_idx >= self.start_step and (step_idx - self.start_step) % self.every_n_steps == 0
