"""Axis-aligned voxel grids in the ego frame.

The ego frame follows nuScenes/Occ3D: x forward, y left, z up, metres. A grid covers
``[x_min, x_max) x [y_min, y_max) x [z_min, z_max)`` and voxel ``(i, j, k)`` spans
``[x_min + i*dx, x_min + (i+1)*dx)`` and so on; label tensors are indexed ``[i, j, k]``
(shape ``(X, Y, Z)``), exactly like Occ3D's ``semantics`` arrays.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["GridSpec"]


@dataclass(frozen=True)
class GridSpec:
    """A voxel grid: its metric range and voxel size.

    Args:
        range: ``(x_min, y_min, z_min, x_max, y_max, z_max)`` in metres, ego frame.
        voxel_size: edge length in metres; one number (cubic voxels) or ``(dx, dy, dz)``.

    Example:
        >>> g = GridSpec(range=(-40, -40, -1, 40, 40, 5.4), voxel_size=0.4)
        >>> g.shape
        (200, 200, 16)
    """

    range: tuple[float, float, float, float, float, float]
    voxel_size: tuple[float, float, float]

    def __init__(self, range: Sequence[float], voxel_size: float | Sequence[float]) -> None:  # noqa: A002
        rng = tuple(float(v) for v in range)
        if len(rng) != 6:
            raise ValueError(f"grid range must have 6 numbers (x_min, y_min, z_min, x_max, y_max, z_max), got {list(range)}")
        vs = (float(voxel_size),) * 3 if isinstance(voxel_size, (int, float)) else tuple(float(v) for v in voxel_size)
        if len(vs) != 3 or min(vs) <= 0:
            raise ValueError(f"grid voxel_size must be a positive number or 3 positive numbers, got {voxel_size}")
        for a in range_axes():
            if rng[a + 3] <= rng[a]:
                raise ValueError(f"grid range max must exceed min on axis {'xyz'[a]}, got {list(range)}")
            n = (rng[a + 3] - rng[a]) / vs[a]
            if abs(n - round(n)) > 1e-4:
                raise ValueError(f"grid extent on axis {'xyz'[a]} ({rng[a + 3] - rng[a]:g} m) is not a multiple of voxel size {vs[a]:g}")
        object.__setattr__(self, "range", rng)
        object.__setattr__(self, "voxel_size", vs)

    @classmethod
    def from_config(cls, cfg: GridSpec | dict | Sequence) -> GridSpec:
        """Build from a config mapping ``{range: [...], voxel_size: ...}`` or pass a GridSpec through."""
        if isinstance(cfg, GridSpec):
            return cfg
        return cls(range=cfg["range"], voxel_size=cfg["voxel_size"])

    def to_dict(self) -> dict:
        """The config form of this grid (inverse of :meth:`from_config`)."""
        return {"range": list(self.range), "voxel_size": list(self.voxel_size)}

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(X, Y, Z)``: voxel counts along x, y, z."""
        return tuple(round((self.range[a + 3] - self.range[a]) / self.voxel_size[a]) for a in range_axes())  # type: ignore[return-value]

    @property
    def lower(self) -> tuple[float, float, float]:
        """Minimum corner ``(x_min, y_min, z_min)``."""
        return self.range[:3]  # type: ignore[return-value]

    @property
    def upper(self) -> tuple[float, float, float]:
        """Maximum corner ``(x_max, y_max, z_max)``."""
        return self.range[3:]  # type: ignore[return-value]

    def _lower_size(self, ref: Tensor) -> tuple[Tensor, Tensor]:
        lower = torch.tensor(self.lower, dtype=ref.dtype, device=ref.device)
        size = torch.tensor(self.voxel_size, dtype=ref.dtype, device=ref.device)
        return lower, size

    def index_to_coord(self, index: Tensor) -> Tensor:
        """Voxel centres of integer indices.

        Args:
            index: ``(..., 3)`` integer ``(i, j, k)``.

        Returns:
            ``(..., 3)`` float32 ego-frame coordinates of the voxel centres, metres.
        """
        idx = index.to(torch.float64)
        lower, size = self._lower_size(idx)
        return (lower + (idx + 0.5) * size).to(torch.float32)

    def coord_to_index(self, coord: Tensor) -> Tensor:
        """Index of the voxel containing each point (may lie outside the grid; see :meth:`contains`).

        Args:
            coord: ``(..., 3)`` ego-frame points, metres.

        Returns:
            ``(..., 3)`` int64 ``(i, j, k)``.
        """
        c = coord.to(torch.float64)
        lower, size = self._lower_size(c)
        return torch.floor((c - lower) / size).to(torch.int64)

    def contains(self, coord: Tensor) -> Tensor:
        """``(...)`` bool: whether each ``(..., 3)`` point lies inside the grid's range."""
        c = coord.to(torch.float64)
        lower = torch.tensor(self.lower, dtype=c.dtype, device=c.device)
        upper = torch.tensor(self.upper, dtype=c.dtype, device=c.device)
        return ((c >= lower) & (c < upper)).all(dim=-1)

    def index_in_bounds(self, index: Tensor) -> Tensor:
        """``(...)`` bool: whether each ``(..., 3)`` integer index addresses a voxel of this grid."""
        shape = torch.tensor(self.shape, device=index.device)
        return ((index >= 0) & (index < shape)).all(dim=-1)

    def centers(self, device: torch.device | str | None = None) -> Tensor:
        """``(X, Y, Z, 3)`` float32 ego-frame centres of every voxel."""
        axes = [
            self.lower[a] + (torch.arange(n, device=device, dtype=torch.float64) + 0.5) * self.voxel_size[a]
            for a, n in enumerate(self.shape)
        ]
        return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).to(torch.float32)

    def normalize(self, coord: Tensor) -> Tensor:
        """Map ego-frame points to ``[-1, 1]`` per axis (``-1``/``1`` are the grid's outer faces).

        This is the convention of ``torch.nn.functional.grid_sample(..., align_corners=False)``
        for a volume laid out ``(N, C, X, Y, Z)`` once the last axis is reversed to
        ``(z, y, x)`` order; :func:`occplug.geometry.sample_volume` does that for you.
        """
        lower = torch.tensor(self.lower, dtype=coord.dtype, device=coord.device)
        upper = torch.tensor(self.upper, dtype=coord.dtype, device=coord.device)
        return (coord - lower) / (upper - lower) * 2.0 - 1.0


def range_axes() -> range:
    """The three spatial axes, 0..2 (named for readability at call sites)."""
    return range(3)
