"""The numba kernel of :mod:`occplug.geometry.raycast_numba` (imported only when numba is installed).

Compiled on first call and cached on disk by numba (``cache=True``), so later processes load it.
"""

from __future__ import annotations

import numba
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

__all__ = ["walk"]


@intrinsic
def fma(typingctx, a, b, c):  # noqa: ARG001 (numba's intrinsic signature)
    def codegen(context, builder, signature, args):  # noqa: ARG001
        f64 = ir.DoubleType()
        fn = builder.module.declare_intrinsic("llvm.fma", [f64], ir.FunctionType(f64, [f64, f64, f64]))
        return builder.call(fn, args)

    return types.float64(types.float64, types.float64, types.float64), codegen


@numba.njit(cache=True, nogil=True)
def _boundary(i, v, o, fused):
    """``o + i * v`` as ``torch.addcmul`` rounds it here: in one rounding (``fused``) or two."""
    return fma(i, v, o) if fused else o + i * v


@numba.njit(cache=True, nogil=True)
def walk(ray, index, t_entry, t_stop, offset, inv, step, bits, strides, grids, out_index, out_entry, out_exit, fused):
    all_grids = (1 << grids) - 1
    # the grid's shape, from the row-major strides: a ray whose index leaves it stops (the exit distance, computed by
    # torch, normally stops it first; the test keeps an exit that torch rounded differently from reading past the grid)
    nx, ny, nz = bits.shape[0] // strides[0], strides[0] // strides[1], strides[1]
    for row in range(ray.shape[0]):
        r = ray[row]
        i0, i1, i2 = index[row, 0], index[row, 1], index[row, 2]
        o0, o1, o2 = offset[row, 0], offset[row, 1], offset[row, 2]
        v0, v1, v2 = inv[row, 0], inv[row, 1], inv[row, 2]
        s0, s1, s2 = step[row, 0], step[row, 1], step[row, 2]
        flat = int(i0) * strides[0] + int(i1) * strides[1] + int(i2) * strides[2]
        t = t_entry[row]
        stop = t_stop[row]
        pending = all_grids
        while True:
            t0, t1, t2 = _boundary(i0, v0, o0, fused), _boundary(i1, v1, o1, fused), _boundary(i2, v2, o2, fused)
            t_next = min(t0, t1, t2)
            found = bits[flat] & pending
            if found:
                for g in range(grids):
                    if found & (1 << g):
                        out_index[g, r, 0] = int(i0)
                        out_index[g, r, 1] = int(i1)
                        out_index[g, r, 2] = int(i2)
                        out_entry[g, r] = t
                        out_exit[g, r] = t_next
                pending &= ~found
                if pending == 0:
                    break
            if t0 == t_next:
                i0 += s0
                flat += int(s0) * strides[0]
            if t1 == t_next:
                i1 += s1
                flat += int(s1) * strides[1]
            if t2 == t_next:
                i2 += s2
                flat += int(s2) * strides[2]
            t = t_next
            if not t_next < stop:
                break
            if not (0 <= i0 < nx and 0 <= i1 < ny and 0 <= i2 < nz):
                break
