"""Axis-aligned scene contraction (QueryOcc, Eq. 3).

Coordinates are first normalised by the near-field half-extent, ``phi_bar = x / near``; then
each axis is contracted independently:

    f(phi_bar) = kappa * phi_bar                              if |phi_bar| <= 1
               = sign(phi_bar) * (1 - (1 - kappa) / |phi_bar|)  otherwise

so the near field ``|x| <= near`` maps linearly onto ``[-kappa, kappa]`` and the unbounded far
field onto ``(kappa, 1)``. Unlike spherical contraction the map keeps rectangles rectangular.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["contract", "uncontract"]


def contract(x: Tensor, near: Tensor | float, kappa: float = 0.5) -> Tensor:
    """Contract coordinates ``x`` (any shape; ``near`` broadcasts against it) into ``(-1, 1)``."""
    if not 0.0 < kappa < 1.0:
        raise ValueError(f"kappa must lie in (0, 1), got {kappa}")
    phi = x / near
    mag = phi.abs()
    far = torch.sign(phi) * (1.0 - (1.0 - kappa) / mag.clamp_min(1.0))
    return torch.where(mag <= 1.0, kappa * phi, far)


def uncontract(y: Tensor, near: Tensor | float, kappa: float = 0.5) -> Tensor:
    """Exact inverse of :func:`contract` for ``|y| < 1``."""
    mag = y.abs()
    far = torch.sign(y) * (1.0 - kappa) / (1.0 - mag).clamp_min(1e-12)
    return torch.where(mag <= kappa, y / kappa, far) * near
