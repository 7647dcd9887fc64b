"""Bird's-eye views of occupancy grids: class maps, error maps and the pixel layout they share.

Every BEV here is an ``(X, Y)`` array over the columns of a label grid (``[i, j]`` = the column
of voxels ``(i, j, :)``, ego frame). :func:`to_image` turns it into a picture seen from above
with the ego's forward direction (+x) up and its left (+y) to the left, one pixel per column:

* image row ``r = X - 1 - i`` (top row = largest x, ahead of the ego),
* image column ``c = Y - 1 - j`` (left column = largest y, the ego's left).

:func:`bev_pixel` maps an ego-frame point to that pixel and :func:`image_extent` gives the
matplotlib ``extent`` that puts metric ego coordinates on the axes.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from occplug.geometry import GridSpec

from .style import ERROR_COLORS, Palette

__all__ = [
    "CORRECT",
    "EMPTY",
    "FALSE_OCCUPIED",
    "MISSED",
    "WRONG_CLASS",
    "bev_pixel",
    "bev_rgb",
    "column_mask",
    "error_codes",
    "error_rgb",
    "image_extent",
    "to_image",
    "top_down",
]

#: Error-map codes (see :func:`error_codes`); colours and names in :mod:`occplug.viz.style`.
EMPTY, CORRECT, WRONG_CLASS, MISSED, FALSE_OCCUPIED = range(5)


def _highest(mask: Tensor) -> tuple[Tensor, Tensor]:
    """For a ``(X, Y, Z)`` bool mask: ``(X, Y)`` int64 z-index of the highest true voxel of each
    column and ``(X, Y)`` bool whether the column has one (the index is 0 where it has none)."""
    z = mask.shape[-1]
    any_ = mask.any(dim=-1)
    top = (z - 1) - mask.flip(-1).to(torch.uint8).argmax(dim=-1)
    return torch.where(any_, top, torch.zeros_like(top)), any_


def top_down(labels: Tensor, palette: Palette, valid: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """The class of the highest non-free voxel of every column.

    Args:
        labels: ``(X, Y, Z)`` integer class ids.
        palette: says which ids are free / ignored.
        valid: optional ``(X, Y, Z)`` bool; voxels outside it are treated as free.

    Returns:
        ``classes``: ``(X, Y)`` int64, the class id of the highest occupied voxel, ``-1`` for an
        empty column; ``height``: ``(X, Y)`` int64 z-index of that voxel, ``-1`` for an empty column.
    """
    labels = labels.long()
    occ = palette.occupied(labels)
    if valid is not None:
        occ &= valid.bool()
    top, any_ = _highest(occ)
    cls = labels.gather(-1, top[..., None])[..., 0]
    return torch.where(any_, cls, -1), torch.where(any_, top, -1)


def error_codes(gt: Tensor, pred: Tensor, palette: Palette, valid: Tensor | None = None) -> Tensor:
    """A top-down view of the voxel-wise errors of a prediction.

    Each voxel is *occupied* in the truth and/or the prediction (free and ignored ids are not);
    every column shows the highest voxel occupied in either, coded as

    * :data:`CORRECT` (1): occupied in both, same class;
    * :data:`WRONG_CLASS` (2): occupied in both, different classes;
    * :data:`MISSED` (3): occupied in the truth, free in the prediction;
    * :data:`FALSE_OCCUPIED` (4): free in the truth, occupied in the prediction;
    * :data:`EMPTY` (0): the column is free in both.

    Args:
        gt, pred: ``(X, Y, Z)`` integer class ids on the same grid.
        palette: free / ignore ids; a voxel whose *truth* is the ignore id is skipped.
        valid: optional ``(X, Y, Z)`` bool of voxels to judge (e.g. not ``voxel_invalid``).

    Returns:
        ``(X, Y)`` int64 codes.
    """
    if gt.shape != pred.shape:
        raise ValueError(f"ground truth {tuple(gt.shape)} and prediction {tuple(pred.shape)} differ in shape")
    gt, pred = gt.long(), pred.long()
    judged = torch.ones_like(gt, dtype=torch.bool) if valid is None else valid.bool().clone()
    if palette.ignore_label is not None:
        judged &= gt != palette.ignore_label
    g_occ = palette.occupied(gt) & judged
    p_occ = palette.occupied(pred) & judged
    top, any_ = _highest(g_occ | p_occ)

    def at_top(t: Tensor) -> Tensor:
        return t.gather(-1, top[..., None])[..., 0]

    g, p = at_top(g_occ), at_top(p_occ)
    same = at_top(gt) == at_top(pred)
    codes = torch.full(gt.shape[:2], EMPTY, dtype=torch.int64, device=gt.device)
    codes[g & p & same] = CORRECT
    codes[g & p & ~same] = WRONG_CLASS
    codes[g & ~p] = MISSED
    codes[~g & p] = FALSE_OCCUPIED
    codes[~any_] = EMPTY
    return codes


def column_mask(mask: Tensor) -> Tensor:
    """``(X, Y)`` bool: columns with at least one true voxel of a ``(X, Y, Z)`` mask (e.g. the
    camera visibility mask seen from above)."""
    return mask.bool().any(dim=-1)


def to_image(bev: Tensor | np.ndarray) -> np.ndarray:
    """``(X, Y, ...)`` grid-indexed BEV -> ``(X, Y, ...)`` image rows/columns (forward up, left left)."""
    arr = bev.detach().cpu().numpy() if isinstance(bev, Tensor) else np.asarray(bev)
    return np.ascontiguousarray(arr[::-1, ::-1])


def bev_rgb(labels: Tensor, palette: Palette, valid: Tensor | None = None) -> np.ndarray:
    """``(X, Y, 3)`` uint8 image of the top-down class map (:func:`top_down`, :func:`to_image`);
    empty columns are the palette background."""
    classes, _ = top_down(labels, palette, valid)
    return to_image(palette.colorize(classes))


def error_rgb(codes: Tensor) -> np.ndarray:
    """``(X, Y, 3)`` uint8 image of :func:`error_codes` in :data:`~occplug.viz.style.ERROR_COLORS`."""
    lut = np.asarray(ERROR_COLORS, dtype=np.uint8)
    return to_image(lut[codes.cpu().numpy()])


def bev_pixel(grid: GridSpec, points: Tensor) -> Tensor:
    """``(..., 2)`` int64 image ``(row, col)`` of the BEV pixel showing each ego-frame point
    ``(..., 2 or 3)`` (x, y[, z]); pixels outside the image are returned as computed."""
    idx = grid.coord_to_index(torch.cat([points[..., :2], torch.zeros_like(points[..., :1])], -1))
    x, y, _ = grid.shape
    return torch.stack([x - 1 - idx[..., 0], y - 1 - idx[..., 1]], -1)


def image_extent(grid: GridSpec) -> tuple[float, float, float, float]:
    """matplotlib ``imshow(..., extent=...)`` for a :func:`to_image` picture (origin ``upper``):
    the horizontal axis is ego y (decreasing to the right), the vertical axis ego x, in metres."""
    x0, y0, _, x1, y1, _ = grid.range
    return (y1, y0, x0, x1)
