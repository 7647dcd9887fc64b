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
def walk(ray, index, t_entry, t_stop, offset, inv, step, bits, strides, grids, out_index, out_entry, out_exit):
    all_grids = (1 << grids) - 1
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
            t0, t1, t2 = fma(i0, v0, o0), fma(i1, v1, o1), fma(i2, v2, o2)
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
