"""Hilbert-curve serialisation of a 3D feature grid to a 1D token sequence and back (OccLE Appendix A).

OccLE's Dual Mamba linearises each ``(X, Y, Z)`` grid along a Hilbert curve before its Mamba block
and restores the grid afterwards. A classic Hilbert curve needs a cube with a power-of-two side; the
stage grids of a driving scene are neither (``32 x 32 x 4``, ``24 x 40 x 6``), so this module uses the
*generalised* Hilbert curve ("gilbert", Jakub Červený, 2018, BSD-2-Clause), reimplemented here with
the reference ``gilbert3d``'s cutting rules: the cuboid is cut recursively into two (along one long
axis) or three / five sub-cuboids (the Hilbert pattern), each cut placed so that the parts keep even
sides where possible, until a sub-cuboid is a single row of cells, which is walked straight.

What the curve guarantees (a property of the construction, measured over every shape with sides 1..12
and on the stage shapes; the tests repeat the checks on a subset):

* it visits every cell exactly once (a permutation of ``range(X * Y * Z)``), for any shape;
* when every side is even, every step goes to a face neighbour (Manhattan distance 1); the same holds
  when some sides are 1 and the others even (``8 x 8 x 1``);
* otherwise an occasional step is diagonal (Manhattan distance 2 to 4 in the shapes measured): >= 95 %
  of the steps are unit steps once every side is >= 4 (worst measured: ``7 x 7 x 7``, 95.3 %), fewer on
  tiny odd grids (``2 x 2 x 3``: 10 of 11; ``1 x 2 x 3``: 4 of 5).

Flat 3D index: C order of ``(X, Y, Z)``, i.e. ``x * Y * Z + y * Z + z`` -- the order of
``x.flatten(2)`` for a ``(B, C, X, Y, Z)`` tensor.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

__all__ = ["deserialize", "hilbert_curve", "hilbert_permutation", "serialize"]

_Vec = tuple[int, int, int]


def _add(*vs: _Vec) -> _Vec:
    return (sum(v[0] for v in vs), sum(v[1] for v in vs), sum(v[2] for v in vs))


def _neg(v: _Vec) -> _Vec:
    return (-v[0], -v[1], -v[2])


def _sign(v: _Vec) -> _Vec:
    return ((v[0] > 0) - (v[0] < 0), (v[1] > 0) - (v[1] < 0), (v[2] > 0) - (v[2] < 0))


def _length(v: _Vec) -> int:
    # every edge vector is axis-aligned: its one non-zero component is the length (with a sign)
    return abs(v[0] + v[1] + v[2])


def _half(v: _Vec) -> _Vec:
    # floor division like the reference algorithm (-5 // 2 == -3), then rounded away from an odd
    # half so that sub-cuboids keep even sides where the parent allows it
    h = (v[0] // 2, v[1] // 2, v[2] // 2)
    if _length(h) % 2 and _length(v) > 2:
        h = _add(h, _sign(v))
    return h


def _gilbert(p: _Vec, a: _Vec, b: _Vec, c: _Vec, runs: list[tuple[_Vec, _Vec, int]]) -> None:
    """Append the curve through the cuboid at corner ``p`` spanned by ``a`` (major), ``b``, ``c`` as straight runs.

    A run ``(start, step, n)`` is ``n`` cells from ``start`` in unit steps ``step``.
    """
    w, h, d = _length(a), _length(b), _length(c)
    if h == 1 and d == 1:
        runs.append((p, _sign(a), w))
        return
    if w == 1 and d == 1:
        runs.append((p, _sign(b), h))
        return
    if w == 1 and h == 1:
        runs.append((p, _sign(c), d))
        return
    da, db, dc = _sign(a), _sign(b), _sign(c)
    a2, b2, c2 = _half(a), _half(b), _half(c)
    a_rest, b_rest, c_rest = _add(a, _neg(a2)), _add(b, _neg(b2)), _add(c, _neg(c2))
    a_end = _add(a, _neg(da))  # from the first to the last cell along a
    if 2 * w > 3 * h and 2 * w > 3 * d:
        # long along a: two halves side by side
        _gilbert(p, a2, b, c, runs)
        _gilbert(_add(p, a2), a_rest, b, c, runs)
    elif 3 * h > 4 * d:
        # thin along c: the 2D Hilbert pattern in the (a, b) plane -- up, across, down
        _gilbert(p, b2, c, a2, runs)
        _gilbert(_add(p, b2), a, b_rest, c, runs)
        _gilbert(_add(p, a_end, b2, _neg(db)), _neg(b2), c, _neg(a_rest), runs)
    elif 3 * d > 4 * h:
        # thin along b: the same pattern in the (a, c) plane
        _gilbert(p, c2, a2, b, runs)
        _gilbert(_add(p, c2), a, b, c_rest, runs)
        _gilbert(_add(p, a_end, c2, _neg(dc)), _neg(c2), _neg(a_rest), b, runs)
    else:
        # the 3D Hilbert pattern: five sub-cuboids
        _gilbert(p, b2, c2, a2, runs)
        _gilbert(_add(p, b2), c, a2, b_rest, runs)
        _gilbert(_add(p, b2, _neg(db), c, _neg(dc)), a, _neg(b2), _neg(c_rest), runs)
        _gilbert(_add(p, a_end, b2, c, _neg(dc)), _neg(c), _neg(a_rest), b_rest, runs)
        _gilbert(_add(p, a_end, b2, _neg(db)), _neg(b2), c2, _neg(a_rest), runs)


def _check_shape(shape: tuple[int, ...]) -> tuple[int, int, int]:
    if len(shape) != 3 or any(int(s) < 1 for s in shape):
        raise ValueError(f"hilbert: need a 3D grid shape of positive sizes, got {tuple(shape)}")
    return int(shape[0]), int(shape[1]), int(shape[2])


@functools.lru_cache(maxsize=64)
def _curve(shape: tuple[int, int, int]) -> np.ndarray:
    # numpy, not torch: a cached torch tensor made while torch.export traces would be a fake tensor
    sx, sy, sz = shape
    runs: list[tuple[_Vec, _Vec, int]] = []
    # the longest side is the major axis, as in the reference algorithm
    if sx >= sy and sx >= sz:
        _gilbert((0, 0, 0), (sx, 0, 0), (0, sy, 0), (0, 0, sz), runs)
    elif sy >= sx and sy >= sz:
        _gilbert((0, 0, 0), (0, sy, 0), (sx, 0, 0), (0, 0, sz), runs)
    else:
        _gilbert((0, 0, 0), (0, 0, sz), (sx, 0, 0), (0, sy, 0), runs)
    start = np.array([r[0] for r in runs], dtype=np.int64)  # (R, 3)
    step = np.array([r[1] for r in runs], dtype=np.int64)
    count = np.array([r[2] for r in runs], dtype=np.int64)
    run_of_cell = np.repeat(np.arange(len(runs)), count)
    first_cell = np.cumsum(count) - count
    offset = np.arange(int(count.sum())) - first_cell[run_of_cell]
    xyz = start[run_of_cell] + step[run_of_cell] * offset[:, None]
    xyz.flags.writeable = False
    return xyz


def hilbert_curve(shape: tuple[int, int, int]) -> Tensor:
    """Grid coordinates of the generalised Hilbert curve through an ``(X, Y, Z)`` grid, in visiting order.

    Args:
        shape: ``(X, Y, Z)``, any positive sizes.

    Returns:
        ``(X * Y * Z, 3)`` int64 cell indices ``(x, y, z)``; row ``i`` is the ``i``-th cell visited.
        Computed once per shape (a fresh copy each call).
    """
    return torch.from_numpy(_curve(_check_shape(tuple(shape))).copy())


@functools.lru_cache(maxsize=64)
def _permutation(shape: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    xyz = _curve(shape)
    perm = (xyz[:, 0] * shape[1] + xyz[:, 1]) * shape[2] + xyz[:, 2]
    inverse = np.empty_like(perm)
    inverse[perm] = np.arange(perm.size)
    perm.flags.writeable = inverse.flags.writeable = False
    return perm, inverse


def hilbert_permutation(shape: tuple[int, int, int]) -> tuple[Tensor, Tensor]:
    """The Hilbert order of an ``(X, Y, Z)`` grid as a permutation of its flat (C-order) cell indices.

    Args:
        shape: ``(X, Y, Z)``, any positive sizes (non-power-of-two and anisotropic included).

    Returns:
        ``(perm, inverse)``, both ``(X * Y * Z,)`` int64 on the CPU: ``perm[i]`` is the flat 3D index
        ``x * Y * Z + y * Z + z`` of the ``i``-th cell along the curve (1D order -> 3D), and
        ``inverse[j]`` is the position along the curve of flat cell ``j`` (3D -> 1D), so
        ``perm[inverse] == inverse[perm] == arange``. Computed once per shape (fresh copies each
        call).
    """
    perm, inverse = _permutation(_check_shape(tuple(shape)))
    return torch.from_numpy(perm.copy()), torch.from_numpy(inverse.copy())


@functools.lru_cache(maxsize=64)
def _cached_on(shape: tuple[int, int, int], device: torch.device) -> tuple[Tensor, Tensor]:
    perm, inverse = _permutation(shape)
    with torch.inference_mode(False):  # made under inference_mode, a cached index could not serve training later
        return torch.tensor(perm, device=device), torch.tensor(inverse, device=device)


def _permutation_on(shape: tuple[int, int, int], device: torch.device) -> tuple[Tensor, Tensor]:
    if torch.compiler.is_compiling():  # while tracing, fresh tensors (graph constants), never cached fake ones
        perm, inverse = _permutation(shape)
        return torch.tensor(perm, device=device), torch.tensor(inverse, device=device)
    return _cached_on(shape, device)


def serialize(x: Tensor) -> Tensor:
    """Read a feature grid along its Hilbert curve: ``(B, C, X, Y, Z)`` -> ``(B, L, C)`` tokens, ``L = X * Y * Z``.

    Token ``i`` is the cell ``perm[i]`` of :func:`hilbert_permutation` (any dtype or device).
    """
    if x.dim() != 5:
        raise ValueError(f"serialize: expected (B, C, X, Y, Z), got shape {tuple(x.shape)}")
    perm, _ = _permutation_on(_check_shape(tuple(x.shape[2:])), x.device)
    return x.flatten(2).index_select(2, perm).transpose(1, 2)


def deserialize(seq: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """Put Hilbert-ordered tokens back on their grid: ``(B, L, C)`` -> ``(B, C, X, Y, Z)``; inverts :func:`serialize`.

    Args:
        seq: ``(B, L, C)`` with ``L = X * Y * Z`` tokens in the curve's order.
        shape: ``(X, Y, Z)`` of the grid.
    """
    sx, sy, sz = _check_shape(tuple(shape))
    if seq.dim() != 3 or seq.shape[1] != sx * sy * sz:
        raise ValueError(
            f"deserialize: expected (B, {sx * sy * sz}, C) for grid {(sx, sy, sz)}, got {tuple(seq.shape)}"
        )
    _, inverse = _permutation_on((sx, sy, sz), seq.device)
    return seq.transpose(1, 2).index_select(2, inverse).unflatten(2, (sx, sy, sz))
