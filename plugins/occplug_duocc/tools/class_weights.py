"""The public DuOcc code's occupancy CE class weights, from a training split's class counts.

The code (``duocc_head.py`` ``loss_occ_pred``) weights its occupancy CE by ``5 / ln(f_c)`` over the raw voxel counts
``f_c`` of nuScenes (its ``nusc_class_frequencies``) and halves the free class's weight; the paper does not give
them. :func:`duocc_class_weights` computes the same from any counts (``occplug data stats`` prints them);
``python -m occplug_duocc.tools.fit_class_weights`` counts a config's training split and writes a config overlay.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from occplug.data import inverse_log_weights

__all__ = ["CODE_EPS", "CODE_FREE_FACTOR", "CODE_SCALE", "duocc_class_weights"]

#: the numerator of the code's ``5 / ln(f)``.
CODE_SCALE = 5.0
#: the code's factor on the free class's weight.
CODE_FREE_FACTOR = 0.5
#: what the code adds to each count before the logarithm (``1 / np.log(f + 0.001)``); below float32 precision at
#: nuScenes' counts, about 1e-6 relative at a count of a hundred.
CODE_EPS = 0.001


def duocc_class_weights(
    counts: Tensor | Sequence[float],
    free_index: int = -1,
    free_factor: float = CODE_FREE_FACTOR,
    eps: float = 0.0,
) -> Tensor:
    """``5 / ln(f_c + eps)`` per class, the free class's times ``free_factor``.

    Args:
        counts: ``(K,)`` raw voxel counts per label id over the training split (free included).
        free_index: the free class's position (Occ3D: the last, 17).
        free_factor: the factor on free's weight (the code: 0.5).
        eps: added to the counts before the logarithm (the code: :data:`CODE_EPS`; default 0, the value the
            shipped rounded overlays were made with).

    Returns:
        ``(K,)`` float32 weights. A class counted at most once (absent from the split; ``ln`` would be 0 or
        undefined) gets the largest weight of the others: it is at least as rare as the rarest seen, and its weight
        only matters on data that holds it.

    Raises:
        ValueError: ``counts`` is not 1-D, or no class was counted more than once.
    """
    f = torch.as_tensor(counts, dtype=torch.float64)
    if f.dim() != 1:
        raise ValueError(f"duocc_class_weights: expected a 1-D list of class counts, got shape {tuple(f.shape)}")
    seen = f > 1
    if not bool(seen.any()):
        raise ValueError(f"duocc_class_weights: no class is counted more than once in {f.tolist()}")
    weights = torch.empty(f.shape[0], dtype=torch.float32)
    weights[seen] = inverse_log_weights(f[seen], scale=CODE_SCALE, eps=eps)
    weights[~seen] = weights[seen].max()
    weights[free_index] = weights[free_index] * free_factor
    return weights
