"""Hungarian matching: the minimum-cost one-to-one assignment of predictions to ground truths (DETR-style losses).

scipy's ``linear_sum_assignment`` solves it. scipy is an optional dependency, imported only when a match runs,
so ``import occplug.nn`` works without it (install ``scipy``, e.g. through ``occplug[duocc]``).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["linear_assignment"]


def linear_assignment(cost: Tensor) -> tuple[Tensor, Tensor]:
    """Minimum-cost one-to-one assignment of a ``(Q, G)`` cost matrix (scipy's Hungarian solver).

    Rows are predictions, columns ground truths; ``min(Q, G)`` pairs are returned, so with more predictions
    than ground truths the unmatched predictions are the background ones. The cost is solved in float64 on the
    CPU, detached. NaN and ``-inf`` costs count as ``1e8`` (as Sparse4D does: the solver rejects them); any
    shape, also empty.

    Returns:
        ``(pred_idx, gt_idx)``, each ``(min(Q, G),)`` int64 on ``cost``'s device, ``pred_idx`` ascending:
        prediction ``pred_idx[i]`` is matched to ground truth ``gt_idx[i]``.

    Raises:
        ImportError: scipy is not installed (one line, how to install it).
    """
    try:
        from scipy.optimize import linear_sum_assignment
    except ImportError as err:  # scipy is optional: only the plugins that match need it
        raise ImportError(
            "Hungarian matching (occplug.nn.linear_assignment) needs scipy, which is not installed: pip install "
            "scipy (or the plugin's extra, e.g. pip install 'occplug[duocc]')"
        ) from err
    if cost.numel() == 0:
        empty = torch.zeros(0, dtype=torch.int64, device=cost.device)
        return empty, empty.clone()
    c = cost.detach().to(device="cpu", dtype=torch.float64)
    c = torch.where(c.isnan() | c.isneginf(), torch.full_like(c, 1e8), c)
    rows, cols = linear_sum_assignment(c.numpy())
    return (
        torch.as_tensor(rows, dtype=torch.int64, device=cost.device),
        torch.as_tensor(cols, dtype=torch.int64, device=cost.device),
    )
