"""A compiled per-ray loop for :func:`~occplug.geometry.raycast.first_hits` on CPU (numba, optional).

The pure-PyTorch walk of :mod:`occplug.geometry.raycast` is the reference. This kernel starts from the
very same per-ray state (the reference's own set-up code: entry distance, start voxel, boundary
offsets and inverse directions, all float64) and then steps each ray voxel by voxel in compiled code,
evaluating every boundary distance with the expression the reference uses, ``offset + index * inv``
rounded as ``torch.addcmul`` rounds it on this machine (once, fused, where torch's CPU kernels use FMA; twice
where they do not, e.g. under ``ATEN_CPU_CAPABILITY=default``: :func:`torch_fuses_addcmul` asks torch), and
the same tie rule (axes whose
boundary distances are equal step together). So it reports the same voxels and the same distances,
bit for bit, as the reference walk on this machine; ``tests/geometry/test_raycast.py`` holds the two
equal. The kernel needs ``numba`` (``pip install occplug[fast]``); without it, or for tensors on a GPU,
``first_hits`` runs the reference walk.

The function is compiled on first use (a few seconds, cached on disk by numba afterwards).
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

__all__ = ["MAX_GRIDS", "available", "first_hits_numba"]

#: The most grids one compiled walk casts through at once (one bit each of an int64 code).
MAX_GRIDS = 62


@functools.cache
def torch_fuses_addcmul() -> bool:
    """Whether ``torch.addcmul`` on CPU float64 rounds ``c + a * b`` once (FMA) here: ``a * b`` of
    ``(1 + 2**-30)**2`` is exactly ``1 + 2**-29 + 2**-60``, whose last term only a fused product keeps."""
    a = torch.full((64,), 1.0 + 2.0**-30, dtype=torch.float64)  # 64: torch's vectorised loop, as the walk's set-up
    c = torch.full((64,), -(1.0 + 2.0**-29), dtype=torch.float64)
    exact = torch.addcmul(c, a, a)
    return bool((exact != 0).all())


@functools.cache
def available() -> bool:
    """Whether the compiled kernel can be used (``numba`` importable)."""
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


def first_hits_numba(occupied: Tensor, walk_state, out_index: Tensor, out_entry: Tensor, out_exit: Tensor) -> None:
    """Fill ``out_*`` (``(G, R, 3)`` int64, ``(G, R)`` float64 twice, CPU, preset to -1 / inf) with the
    first hit of every ray of ``walk_state`` (a :class:`~occplug.geometry.raycast._Walk` just built) in
    each of the ``G`` grids of ``occupied`` ``(G, X, Y, Z)`` bool."""
    grids = occupied.shape[0]
    if grids > MAX_GRIDS:
        raise ValueError(f"first_hits: the compiled walk handles at most {MAX_GRIDS} grids at once, got {grids}")
    flat_occ = occupied.reshape(grids, -1).to(torch.int64)
    bits = (flat_occ << torch.arange(grids)[:, None]).sum(0)
    shape = occupied.shape[1:]
    strides = np.array([shape[1] * shape[2], shape[2], 1], dtype=np.int64)
    state = walk_state

    def arr(t: Tensor) -> np.ndarray:
        return np.ascontiguousarray(t.numpy())

    from ._raycast_kernel import walk

    walk(
        arr(state.ray),
        arr(state.index),
        arr(state.t_entry),
        arr(state.t_stop),
        arr(state.offset),
        arr(state.inv),
        arr(state.step.to(torch.float64)),
        arr(bits),
        strides,
        grids,
        out_index.numpy(),
        out_entry.numpy(),
        out_exit.numpy(),
        torch_fuses_addcmul(),
    )
