"""Axis-aligned voxel grids in the ego frame.

The ego frame follows nuScenes/Occ3D: x forward, y left, z up, metres. A grid covers
``[x_min, x_max) x [y_min, y_max) x [z_min, z_max)`` and voxel ``(i, j, k)`` spans
``[x_min + i*dx, x_min + (i+1)*dx)`` and so on; label tensors are indexed ``[i, j, k]``
(shape ``(X, Y, Z)``), exactly like Occ3D's ``semantics`` arrays.

A grid may carry a :class:`~occplug.geometry.contraction.Contraction` of x and y (z stays
linear): then ``range`` and ``voxel_size`` describe the grid in *contracted* coordinates, every
finite point has an (x, y) cell (far points land in the border cells) and
:meth:`GridSpec.coord_to_index`, :meth:`GridSpec.normalize`, :meth:`GridSpec.index_to_coord` and
:meth:`GridSpec.centers` apply the contraction. Benchmarks evaluate on metric (uncontracted) grids;
read a contracted volume there with :func:`occplug.geometry.sample_volume` at the metric centres.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from .contraction import Contraction, contract, uncontract

__all__ = ["GridSpec"]


@dataclass(frozen=True)
class GridSpec:
    """A voxel grid: its metric range and voxel size.

    Args:
        range: ``(x_min, y_min, z_min, x_max, y_max, z_max)`` in metres, ego frame.
        voxel_size: edge length in metres; one number (cubic voxels) or ``(dx, dy, dz)``.
        contraction: optional axis-aligned contraction of x and y (a :class:`Contraction` or
            ``{near, kappa}``), about the centre of the range; ``None`` (default): a metric grid.

    Example:
        >>> g = GridSpec(range=(-40, -40, -1, 40, 40, 5.4), voxel_size=0.4)
        >>> g.shape
        (200, 200, 16)
    """

    range: tuple[float, float, float, float, float, float]
    voxel_size: tuple[float, float, float]
    contraction: Contraction | None = None

    def __init__(
        self,
        range: Sequence[float],  # noqa: A002
        voxel_size: float | Sequence[float],
        contraction: Contraction | Mapping | None = None,
    ) -> None:
        rng = tuple(float(v) for v in range)
        if len(rng) != 6:
            raise ValueError(
                f"grid range must have 6 numbers (x_min, y_min, z_min, x_max, y_max, z_max), got {list(range)}"
            )
        vs = (float(voxel_size),) * 3 if isinstance(voxel_size, (int, float)) else tuple(float(v) for v in voxel_size)
        if len(vs) != 3 or min(vs) <= 0:
            raise ValueError(f"grid voxel_size must be a positive number or 3 positive numbers, got {voxel_size}")
        for a in range_axes():
            if rng[a + 3] <= rng[a]:
                raise ValueError(f"grid range max must exceed min on axis {'xyz'[a]}, got {list(range)}")
            n = (rng[a + 3] - rng[a]) / vs[a]
            if abs(n - round(n)) > 1e-4:
                raise ValueError(
                    f"grid extent on axis {'xyz'[a]} ({rng[a + 3] - rng[a]:g} m) is not a multiple of voxel size {vs[a]:g}"
                )
        object.__setattr__(self, "range", rng)
        object.__setattr__(self, "voxel_size", vs)
        object.__setattr__(self, "contraction", None if contraction is None else Contraction.from_config(contraction))

    @classmethod
    def from_config(cls, cfg: GridSpec | dict | Sequence) -> GridSpec:
        """Build from a config mapping ``{range: [...], voxel_size: ..., contraction: {near, kappa}}``
        (``contraction`` optional) or pass a GridSpec through."""
        if isinstance(cfg, GridSpec):
            return cfg
        return cls(range=cfg["range"], voxel_size=cfg["voxel_size"], contraction=cfg.get("contraction"))

    def to_dict(self) -> dict:
        """The config form of this grid (inverse of :meth:`from_config`); ``contraction`` only when set."""
        out = {"range": list(self.range), "voxel_size": list(self.voxel_size)}
        if self.contraction is not None:
            out["contraction"] = self.contraction.to_dict()
        return out

    def __repr__(self) -> str:  # as before contraction existed, unless the grid has one
        tail = "" if self.contraction is None else f", contraction={self.contraction!r}"
        return f"GridSpec(range={self.range!r}, voxel_size={self.voxel_size!r}{tail})"

    @property
    def is_contracted(self) -> bool:
        """Whether x and y are contracted (see the module docstring)."""
        return self.contraction is not None

    def contract_coords(self, coord: Tensor) -> Tensor:
        """``(..., 3)`` ego-frame points -> the grid's (contracted) coordinates, same dtype; identity on a metric grid.

        On a contracted axis with range centre ``c`` and half-extent ``R``:
        ``c + R * contract(x - c, near, kappa)``, which lies in ``(c - R, c + R)`` for every finite ``x``.
        """
        if self.contraction is None:
            return coord
        return torch.cat(
            [self._warp_axis(coord[..., a], a, inverse=False).unsqueeze(-1) for a in (0, 1)] + [coord[..., 2:]], dim=-1
        )

    def uncontract_coords(self, coord: Tensor) -> Tensor:
        """Inverse of :meth:`contract_coords` (for points strictly inside the range in x and y)."""
        if self.contraction is None:
            return coord
        return torch.cat(
            [self._warp_axis(coord[..., a], a, inverse=True).unsqueeze(-1) for a in (0, 1)] + [coord[..., 2:]], dim=-1
        )

    def _warp_axis(self, x: Tensor, axis: int, inverse: bool) -> Tensor:
        assert self.contraction is not None
        mid = (self.range[axis] + self.range[axis + 3]) / 2
        half = (self.range[axis + 3] - self.range[axis]) / 2
        near, kappa = self.contraction.near[axis], self.contraction.kappa
        if inverse:
            return mid + uncontract((x - mid) / half, near, kappa)
        return mid + half * contract(x - mid, near, kappa)

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
            ``(..., 3)`` float32 ego-frame coordinates of the voxel centres, metres (uncontracted
            on a contracted grid).
        """
        idx = index.to(torch.float64)
        lower, size = self._lower_size(idx)
        return self.uncontract_coords(lower + (idx + 0.5) * size).to(torch.float32)

    def coord_to_index(self, coord: Tensor) -> Tensor:
        """Index of the voxel containing each point (may lie outside the grid; see :meth:`contains`).

        Args:
            coord: ``(..., 3)`` ego-frame points, metres.

        Returns:
            ``(..., 3)`` int64 ``(i, j, k)``. On a contracted grid ``i`` and ``j`` always address a
            cell: points beyond the far edge land in the border cells.
        """
        c = coord.to(torch.float64)
        lower, size = self._lower_size(c)
        if self.contraction is None:
            return torch.floor((c - lower) / size).to(torch.int64)
        idx = torch.floor((self.contract_coords(c) - lower) / size).to(torch.int64)
        # contract() maps every finite x strictly inside; the clamp only absorbs round-off at ~1e16 m.
        x, y, _ = self.shape
        return torch.cat([idx[..., :1].clamp(0, x - 1), idx[..., 1:2].clamp(0, y - 1), idx[..., 2:]], dim=-1)

    def contains(self, coord: Tensor) -> Tensor:
        """``(...)`` bool: whether each ``(..., 3)`` point lies inside the grid's range (contracted: its z range)."""
        c = coord.to(torch.float64)
        lower = torch.tensor(self.lower, dtype=c.dtype, device=c.device)
        upper = torch.tensor(self.upper, dtype=c.dtype, device=c.device)
        inside = (c >= lower) & (c < upper)
        if self.contraction is not None:
            return inside[..., 2]
        return inside.all(dim=-1)

    def index_in_bounds(self, index: Tensor) -> Tensor:
        """``(...)`` bool: whether each ``(..., 3)`` integer index addresses a voxel of this grid."""
        shape = torch.tensor(self.shape, device=index.device)
        return ((index >= 0) & (index < shape)).all(dim=-1)

    def centers(self, device: torch.device | str | None = None) -> Tensor:
        """``(X, Y, Z, 3)`` float32 ego-frame centres of every voxel (uncontracted on a contracted grid)."""
        axes = [
            self.lower[a] + (torch.arange(n, device=device, dtype=torch.float64) + 0.5) * self.voxel_size[a]
            for a, n in enumerate(self.shape)
        ]
        if self.contraction is not None:
            axes[:2] = [self._warp_axis(axes[a], a, inverse=True) for a in (0, 1)]
        return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).to(torch.float32)

    def normalize(self, coord: Tensor) -> Tensor:
        """Map ego-frame points to ``[-1, 1]`` per axis (``-1``/``1`` are the grid's outer faces).

        This is the convention of ``torch.nn.functional.grid_sample(..., align_corners=False)``
        for a volume laid out ``(N, C, X, Y, Z)`` once the last axis is reversed to
        ``(z, y, x)`` order; :func:`occplug.geometry.sample_volume` does that for you. On a
        contracted grid x and y are contracted first (every finite point maps into ``(-1, 1)``).
        """
        lower = torch.tensor(self.lower, dtype=coord.dtype, device=coord.device)
        upper = torch.tensor(self.upper, dtype=coord.dtype, device=coord.device)
        return (self.contract_coords(coord) - lower) / (upper - lower) * 2.0 - 1.0

    def denormalize(self, norm: Tensor) -> Tensor:
        """Inverse of :meth:`normalize`: ``[-1, 1]`` grid coordinates back to ego-frame points (on a contracted
        grid x and y must lie strictly inside ``(-1, 1)``: the faces are at infinity)."""
        lower = torch.tensor(self.lower, dtype=norm.dtype, device=norm.device)
        upper = torch.tensor(self.upper, dtype=norm.dtype, device=norm.device)
        return self.uncontract_coords((norm + 1.0) / 2.0 * (upper - lower) + lower)


def range_axes() -> range:
    """The three spatial axes, 0..2 (named for readability at call sites)."""
    return range(3)
