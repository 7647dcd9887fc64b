"""What a head answers at continuous points: :class:`QueryResult`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["QueryResult"]


@dataclass
class QueryResult:
    """A head's answer at ``P`` continuous query points per sample.

    Attributes:
        class_logits: ``(B, P, K)`` float logits over the data set's ``K`` label ids (``free`` included).
        occupancy_logit: ``(B, P)`` logit of "occupied", or ``None``. A head without one predicts
            ``free`` as one of its ``K`` classes.
        features: ``(B, P, F)`` predicted feature vectors (e.g. distilled foundation-model features), or ``None``.

    Class ids (:meth:`logits`): without an occupancy logit, ``argmax(class_logits)``. With one (``o``),
    a two-stage decision: a point is ``free`` where ``o < 0`` and otherwise the most likely *occupied*
    class, ``argmax`` of ``class_logits`` over the classes other than ``free`` (whose column is ignored).
    """

    class_logits: Tensor
    occupancy_logit: Tensor | None = None
    features: Tensor | None = None

    def __post_init__(self) -> None:
        if self.class_logits.dim() != 3:
            raise ValueError(f"QueryResult.class_logits must be (B, P, K), got {tuple(self.class_logits.shape)}")
        bp = tuple(self.class_logits.shape[:2])
        if self.occupancy_logit is not None and tuple(self.occupancy_logit.shape) != bp:
            raise ValueError(
                f"QueryResult.occupancy_logit must be (B, P) = {bp}, got {tuple(self.occupancy_logit.shape)}"
            )
        if self.features is not None and (self.features.dim() != 3 or tuple(self.features.shape[:2]) != bp):
            raise ValueError(
                f"QueryResult.features must be (B, P, F) with (B, P) = {bp}, got {tuple(self.features.shape)}"
            )

    def logits(self, free_label: int | None = None, threshold: float = 0.5) -> Tensor:
        """``(B, P, K)`` logits whose ``argmax`` over ``K`` is the class id (see the class docstring).

        Without an occupancy logit these are ``class_logits``. With one, ``free``'s column becomes
        ``max_{c != free} class_logits_c - (o - logit(threshold))``: the best occupied class beats ``free``
        exactly where ``sigmoid(o) > threshold`` (at equality they tie and ``argmax`` takes the lower label
        id), its margin over ``free`` is ``o - logit(threshold)`` (``o`` at the default 0.5), and the other
        columns are ``class_logits`` unchanged.

        Args:
            free_label: label id of ``free``; required when there is an occupancy logit.
            threshold: occupancy probability below which a point is ``free``, in ``(0, 1)``.
        """
        o = self.occupancy_logit
        if o is None:
            return self.class_logits
        if not 0.0 < threshold < 1.0:
            raise ValueError(f"occupancy threshold must lie in (0, 1), got {threshold}")
        if threshold != 0.5:
            o = o - math.log(threshold / (1.0 - threshold))
        k = self.class_logits.shape[-1]
        if free_label is None or not 0 <= free_label < k or k < 2:
            raise ValueError(
                f"a QueryResult with an occupancy logit needs free_label in [0, {k}) and K >= 2, got {free_label}"
            )
        is_free = torch.zeros(k, dtype=torch.bool, device=self.class_logits.device)
        is_free[free_label] = True
        best_occupied = self.class_logits.masked_fill(is_free, float("-inf")).amax(dim=-1)
        return torch.where(is_free, (best_occupied - o).unsqueeze(-1), self.class_logits)
