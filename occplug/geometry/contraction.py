"""Axis-aligned scene contraction (QueryOcc, Eq. 3).

Coordinates are first normalised by the near-field half-extent, ``phi_bar = x / near``; then
each axis is contracted independently:

    f(phi_bar) = kappa * phi_bar                              if |phi_bar| <= 1
               = sign(phi_bar) * (1 - (1 - kappa) / |phi_bar|)  otherwise

so the near field ``|x| <= near`` maps linearly onto ``[-kappa, kappa]`` and the unbounded far
field onto ``(kappa, 1)``. Unlike spherical contraction the map keeps rectangles rectangular.
:class:`Contraction` is the form a :class:`~occplug.geometry.GridSpec` carries (x and y only).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["Contraction", "contract", "uncontract"]


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


@dataclass(frozen=True)
class Contraction:
    """An axis-aligned contraction of a grid's x and y axes (z stays linear).

    On a contracted axis with range centre ``c`` and half-extent ``R``, the ego coordinate ``x``
    maps to ``c + R * contract(x - c, near, kappa)``: the near field ``|x - c| <= near`` fills the
    middle ``kappa`` of the range linearly, everything beyond fills the outer band, and no finite
    point falls outside. Near-field voxels are ``voxel_size * near / (kappa * R)`` metres wide:
    exactly ``voxel_size`` when ``near = kappa * R``.

    Args:
        near: near-field half-extent in metres, one number (x and y) or ``(near_x, near_y)``.
        kappa: share of the half-range given to the near field, in ``(0, 1)``.
    """

    near: tuple[float, float]
    kappa: float

    def __init__(self, near: float | Sequence[float], kappa: float = 0.5) -> None:
        pair = (float(near),) * 2 if isinstance(near, (int, float)) else tuple(float(v) for v in near)
        if len(pair) != 2 or min(pair) <= 0:
            raise ValueError(f"grid contraction near must be a positive number or [near_x, near_y], got {near}")
        if not 0.0 < float(kappa) < 1.0:
            raise ValueError(f"grid contraction kappa must lie in (0, 1), got {kappa}")
        object.__setattr__(self, "near", pair)
        object.__setattr__(self, "kappa", float(kappa))

    @classmethod
    def from_config(cls, cfg: Contraction | Mapping) -> Contraction:
        """From ``{near: ..., kappa: ...}`` (or pass a Contraction through)."""
        if isinstance(cfg, Contraction):
            return cfg
        if not isinstance(cfg, Mapping) or "near" not in cfg or set(cfg) - {"near", "kappa"}:
            raise ValueError(f"grid contraction must be a mapping {{near, kappa}}, got {cfg!r}")
        return cls(near=cfg["near"], kappa=cfg.get("kappa", 0.5))

    def to_dict(self) -> dict:
        """The config form (inverse of :meth:`from_config`)."""
        return {"near": list(self.near), "kappa": self.kappa}
