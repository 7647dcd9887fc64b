"""The selective state-space scan of Mamba (S6; Gu & Dao 2023, Alg. 2), in pure PyTorch.

Per batch element, channel ``d`` and state ``n`` (zero initial state ``h_0 = 0``)::

    dA_t = exp(delta_t * A)               # discretised decay, in (0, 1] when delta >= 0 and A <= 0
    h_t  = dA_t * h_{t-1} + delta_t * B_t * u_t
    y_t  = sum_n C_t[n] * h_t[n] + D * u_t,  then  y_t * silu(z_t)  when a gate z is given

with ``delta``, ``B`` and ``C`` varying along the sequence -- that is what makes the scan *selective*.

Four implementations with one signature (sequence-major layout ``(B, L, ...)``):

* :func:`selective_scan_ref`: a Python loop over the ``L`` time steps, vectorised over batch,
  channels and states, written like ``mamba_ssm``'s own ``selective_scan_ref`` (``dA`` and
  ``delta * B * u`` precomputed, an ``einsum`` per step). The reference.
* :func:`selective_scan_chunked`: the sequence cut into chunks of ``T`` steps, the last state carried
  from chunk to chunk. Two ways to organise the work inside (``within_chunk``):

  - ``"steps"`` (default): every chunk at once, its ``T`` steps in turn. Pass 1 runs all chunks from a
    zero state to get each chunk's own last state; a chunk's decay is ``exp(A * sum_t delta_t)`` (the
    log-space sum of ``log dA`` over the chunk, exponent <= 0); a loop over the ``L / T`` chunks carries
    the state; pass 2 reruns the steps from the carried states and reads ``y``. ``2 T + L / T`` Python
    iterations instead of ``L``, each on ``L / T`` times more data; ``dA`` and ``delta * B * u`` are
    formed per step (``dA`` as ``exp2``, twice as fast as ``exp`` on a CPU) instead of being stored.
  - ``"segsum"``: chunk after chunk, all ``T`` states of a chunk at once from the chunk's log-space
    cumulative sum ``S_t = sum_{r <= t} delta_r * A``: ``h_t = sum_{s <= t} exp(S_t - S_s) dBu_s +
    exp(S_t) h_start``. The segment sums ``S_t - S_s`` (``s <= t``) are <= 0, so no exponent is ever
    positive, whatever the chunk length (the tempting ``exp(S_t) * cumsum(exp(-S_s) * dBu_s)`` overflows
    once ``|S|`` passes ~88 in float32 or ~709 in float64). It does ``T`` times the work of a step (the
    ``T x T`` weights): the fully parallel form, for hardware with many cores; on a CPU it is slower than
    the reference.

  Both only ever exponentiate numbers <= 0 (given ``delta >= 0`` and ``A <= 0``, as in Mamba), and both
  equal the reference to float64 round-off (the tests hold them to 1e-10, gradients included).
* :class:`SelectiveScanFn` (:func:`selective_scan_lean`): the ``"steps"`` chunked scan as an autograd
  Function with a hand-written backward. Autograd through the scans above keeps every step's ``(B, D, N)``
  intermediates (several ``B x L x D x N`` tensors per scan, ~0.3 GB per Mamba block on a ``32 x 32 x 8``
  grid) until backward; the Function keeps only its inputs and the ``(K, B, D, N)`` chunk-start states, and
  its backward runs the adjoint recurrence ``lam_t = C_t g_t + dA_{t+1} lam_{t+1}`` (``grad dA_t = lam_t
  h_{t-1}``, ``grad dBu_t = lam_t``) by chunks, recomputing the states of a few chunks at a time. Same
  gradients as the reference (float64 round-off), about the time of autograd through the chunked scan, a
  fraction of its memory; :func:`selective_scan` uses it whenever gradients are needed.
* ``mamba_ssm``'s CUDA kernel ``selective_scan_fn``, used by :func:`selective_scan` in ``"auto"`` mode
  when the tensors are on CUDA, float32/16/bfloat16, and the ``mamba_ssm`` package is installed with its
  kernel built (a package whose kernel does not load: a warning, then the chunked scan); it is never imported
  otherwise. Measured on an H100 (``B = 2, L = 4096, D = 64, N = 16``, float32): ref 269 ms, chunked 7.6 ms,
  ``mamba_ssm`` 0.19 ms; its output, last state and gradients equal the reference (``test_occle_cuda.py``).

Measured with ``python -m occplug_occle.tools.bench`` (CPU, one thread of a shared machine, ``B = 2, L = 4096, D = 64,
N = 16``, forward without autograd, median of 5): ref 264 ms vs ``"steps"`` (``T = 64``) 37 ms in float32
(7.2x); 386 ms vs 65 ms in float64 (5.9x); ``"segsum"`` (``T = 8``, float64) 526 ms (0.7x). The
reference's time is mostly its ``L`` Python iterations (its ``einsum`` per step alone is about half).
"""

from __future__ import annotations

import functools
import importlib.util
import math
import warnings
from collections.abc import Callable
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "BACKWARD_GROUP_ELEMENTS",
    "ScanMode",
    "SelectiveScanFn",
    "mamba_ssm_kernel",
    "scan_mamba_ssm",
    "selective_scan",
    "selective_scan_chunked",
    "selective_scan_lean",
    "selective_scan_ref",
]

ScanMode = Literal["auto", "chunked", "ref"]


def _check(u: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor, D: Tensor | None, z: Tensor | None) -> None:
    if u.dim() != 3:
        raise ValueError(f"selective scan: u must be (B, L, D), got {tuple(u.shape)}")
    batch, length, dim = u.shape
    if length < 1:
        raise ValueError("selective scan: empty sequence")
    n = A.shape[-1]
    expected = {
        "delta": (delta, (batch, length, dim)),
        "A": (A, (dim, n)),
        "B": (B, (batch, length, n)),
        "C": (C, (batch, length, n)),
    }
    if D is not None:
        expected["D"] = (D, (dim,))
    if z is not None:
        expected["z"] = (z, (batch, length, dim))
    for name, (t, shape) in expected.items():
        if tuple(t.shape) != shape:
            raise ValueError(f"selective scan: {name} must be {shape} for u {tuple(u.shape)}, got {tuple(t.shape)}")


def _work_dtype(dtype: torch.dtype) -> torch.dtype:
    # half types accumulate the state in float32, as mamba_ssm's kernel does
    return torch.promote_types(dtype, torch.float32)


def _finish(y: Tensor, u: Tensor, D: Tensor | None, z: Tensor | None, dtype: torch.dtype) -> Tensor:
    if D is not None:
        y = y + u * D
    if z is not None:
        y = y * F.silu(z.to(y.dtype))
    return y.to(dtype)


def selective_scan_ref(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    D: Tensor | None = None,
    z: Tensor | None = None,
    *,
    return_last_state: bool = False,
) -> Tensor | tuple[Tensor, Tensor]:
    """Selective scan as a loop over time steps (the reference; vectorised over batch, channels and states).

    Args:
        u: ``(B, L, D)`` input sequence.
        delta: ``(B, L, D)`` step sizes (>= 0; Mamba passes ``softplus(...)``).
        A: ``(D, N)`` state matrix diagonal (< 0 in Mamba).
        B, C: ``(B, L, N)`` input and output projections of the state, per step.
        D: ``(D,)`` skip connection, or None.
        z: ``(B, L, D)`` gate (``y * silu(z)``), or None.
        return_last_state: also return ``h_L``.

    Returns:
        ``y`` ``(B, L, D)`` in ``u``'s dtype; with ``return_last_state`` also ``h_L`` ``(B, D, N)`` (float32
        or wider). The state starts at zero.
    """
    _check(u, delta, A, B, C, D, z)
    dtype, work = u.dtype, _work_dtype(u.dtype)
    u, delta, A, B, C = (t.to(work) for t in (u, delta, A, B, C))
    dA = torch.exp(delta.unsqueeze(-1) * A)  # (B, L, D, N)
    dBu = (delta * u).unsqueeze(-1) * B.unsqueeze(2)  # (B, L, D, N)
    h = u.new_zeros(u.shape[0], u.shape[2], A.shape[1])
    ys = []
    for t in range(u.shape[1]):
        h = dA[:, t] * h + dBu[:, t]
        ys.append(torch.einsum("bdn,bn->bd", h, C[:, t]))
    y = _finish(torch.stack(ys, dim=1), u, D, z, dtype)
    return (y, h) if return_last_state else y


def _step(h: Tensor, dt: Tensor, x: Tensor, B: Tensor, A2: Tensor, in_place: bool) -> Tensor:
    """One step ``2^(dt * A2) * h + x * B`` for ``h`` ``(M, D, N)``, ``dt``, ``x`` ``(M, D, 1)``, ``B`` ``(M, 1, N)``.

    ``A2 = A * log2(e)``: ``exp2`` is about twice as fast as ``exp`` on a CPU (SLEEF), and the one extra
    rounding in the exponent costs ~``|dt * A| * eps`` relative, far below the tests' 1e-10.
    """
    if in_place:
        return (dt * A2).exp2_().mul_(h).addcmul_(x, B)
    return torch.addcmul(torch.exp2(dt * A2) * h, x, B)


def _carry(local: Tensor, decay: Tensor, init: Tensor | None = None, reverse: bool = False) -> tuple[Tensor, Tensor]:
    """States entering each chunk: ``start_{c+1} = decay_c * start_c + local_c``, ``start_0 = init`` (0 if None).

    With ``reverse`` the same recurrence runs from the last chunk back (``end_{c-1} = decay_c * end_c + local_c``,
    ``end_{K-1} = init``): the adjoint entering each chunk from its end, in the backward pass.

    Args:
        local: ``(K, B, D, N)`` each chunk's last state from a zero start (chunk-major).
        decay: ``(K, B, D, N)`` each chunk's total decay ``exp(A * sum delta)`` in (0, 1].
        init: ``(B, D, N)`` the state entering the first chunk (the last, with ``reverse``), or None for 0.

    Returns:
        ``(starts (K, B, D, N), final (B, D, N))``.
    """
    state = torch.zeros_like(local[0]) if init is None else init
    order = range(local.shape[0] - 1, -1, -1) if reverse else range(local.shape[0])
    starts: list[Tensor] = [state] * local.shape[0]
    for c in order:
        starts[c] = state
        state = torch.addcmul(local[c], decay[c], state)
    return torch.stack(starts), state


def _chunk_major(x: Tensor, chunks: int, size: int) -> Tensor:
    """``(B, L, F)`` -> ``(T, K * B, F)``, padded with zeros to ``K * T`` steps: step ``t`` of every chunk is one
    contiguous slice, row ``c * B + b`` is chunk ``c`` of batch element ``b`` (consecutive chunks: consecutive rows).
    """
    batch, length = x.shape[:2]
    x = F.pad(x, (0, 0, 0, chunks * size - length))
    return x.view(batch, chunks, size, -1).permute(2, 1, 0, 3).reshape(size, chunks * batch, -1)


def _from_chunk_major(x: Tensor, batch: int, length: int) -> Tensor:
    """Inverse of :func:`_chunk_major`: ``(T, K * B, F)`` -> ``(B, L, F)``."""
    size, rows, features = x.shape
    chunks = rows // batch
    return x.view(size, chunks, batch, features).permute(2, 1, 0, 3).reshape(batch, chunks * size, features)[:, :length]


def _geometry(length: int, chunk_size: int) -> tuple[int, int]:
    """``(T, K)``: steps per chunk and number of chunks."""
    if chunk_size < 1:
        raise ValueError(f"selective scan: chunk_size must be >= 1, got {chunk_size}")
    size = min(chunk_size, length)
    return size, math.ceil(length / size)


def _scan_steps(
    dt: Tensor, xt: Tensor, Bt: Tensor, Ct: Tensor, A: Tensor, batch: int, in_place: bool
) -> tuple[Tensor, Tensor, Tensor]:
    """The ``"steps"`` chunked scan on chunk-major inputs (:func:`_chunk_major`, ``M = K * B`` rows).

    Args:
        dt, xt: ``(T, M, D, 1)`` ``delta`` and ``delta * u``.
        Bt: ``(T, M, 1, N)``; Ct: ``(T, M, N, 1)``.
        A: ``(D, N)``.
        batch: ``B``.
        in_place: step in place (only without autograd).

    Returns:
        ``y`` ``(T, M, D)`` (the state's part, ``sum_n C h``), the states entering each chunk ``(K, B, D, N)``
        and the last state ``(B, D, N)``.
    """
    size, rows, dim = dt.shape[:3]
    chunks, n = rows // batch, A.shape[1]
    A2 = A * math.log2(math.e)
    h = xt.new_zeros(rows, dim, n)
    if chunks > 1:
        for t in range(size):  # pass 1: each chunk's own last state, from zero
            h = _step(h, dt[t], xt[t], Bt[t], A2, in_place)
        decay = torch.exp(dt.sum(0) * A)  # (M, D, N): the chunk's log-space sum, <= 0
        starts, last = _carry(h.view(chunks, batch, dim, n), decay.view(chunks, batch, dim, n))
        h = starts.view(rows, dim, n)
    else:
        starts = h.view(1, batch, dim, n)
    ys = []
    for t in range(size):  # pass 2: the same steps from the carried states
        h = _step(h, dt[t], xt[t], Bt[t], A2, in_place)
        ys.append(torch.bmm(h, Ct[t]).squeeze(-1))
    if chunks == 1:
        last = h
    return torch.stack(ys), starts, last


def selective_scan_chunked(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    D: Tensor | None = None,
    z: Tensor | None = None,
    *,
    chunk_size: int = 64,
    within_chunk: Literal["steps", "segsum"] = "steps",
    return_last_state: bool = False,
) -> Tensor | tuple[Tensor, Tensor]:
    """Selective scan by chunks of ``chunk_size`` steps with the state carried between chunks (module docstring).

    Same arguments and result as :func:`selective_scan_ref`, plus:

    Args:
        chunk_size: ``T``, steps per chunk (any ``L``: the last chunk is padded with ``delta = 0``, which
            leaves the state unchanged). ``"steps"`` is fastest near ``T = sqrt(L)``; ``"segsum"`` holds
            ``(B, T, T, D, N)`` weights, so keep ``T`` small there (8 to 16).
        within_chunk: ``"steps"`` (all chunks at once, the steps of a chunk in turn) or ``"segsum"`` (the
            chunks in turn, all states of a chunk at once from segment sums of ``log dA``).
    """
    _check(u, delta, A, B, C, D, z)
    if within_chunk not in ("steps", "segsum"):
        raise ValueError(f"selective scan: within_chunk must be 'steps' or 'segsum', got {within_chunk!r}")
    dtype, work = u.dtype, _work_dtype(u.dtype)
    u, delta, A, B, C = (t.to(work) for t in (u, delta, A, B, C))
    batch, length, dim = u.shape
    n = A.shape[1]
    size, chunks = _geometry(length, chunk_size)
    dt, xt = (_chunk_major(x, chunks, size).unsqueeze(-1) for x in (delta, delta * u))  # (T, M, D, 1), M = K * B
    Bt, Ct = _chunk_major(B, chunks, size).unsqueeze(2), _chunk_major(C, chunks, size).unsqueeze(-1)
    if within_chunk == "steps":
        # dA and dBu are formed step by step (twice) rather than stored: a (T, M, D, N) tensor is fresh memory
        # on every call, and filling it costs more than recomputing the exponentials. Without autograd each
        # step allocates one (M, D, N) tensor and works in place on it: fewer fresh pages per step.
        in_place = not (torch.is_grad_enabled() and any(t.requires_grad for t in (u, delta, A, B, C)))
        y, _, last = _scan_steps(dt, xt, Bt, Ct, A, batch, in_place)  # (T, M, D)
    else:
        dt, xt = dt.view(size, chunks, batch, dim, 1), xt.view(size, chunks, batch, dim, 1)
        Bt, Ct = Bt.view(size, chunks, batch, 1, n), Ct.view(size, chunks, batch, n, 1)
        above = ~torch.ones(size, size, dtype=torch.bool, device=u.device).tril().view(size, size, 1, 1, 1)
        last = xt.new_zeros(batch, dim, n)
        ys = []
        for c in range(chunks):
            S = torch.cumsum(dt[:, c] * A, dim=0)  # (T, B, D, N): log-space cumsum of log dA within the chunk
            # weights[t, s] = exp(S_t - S_s) = prod_{s < r <= t} dA_r for s <= t (exponent <= 0); 0 above
            weights = (S.unsqueeze(1) - S.unsqueeze(0)).masked_fill(above, float("-inf")).exp()
            dBu = xt[:, c] * Bt[:, c]  # (T, B, D, N)
            states = (weights * dBu.unsqueeze(0)).sum(1) + torch.exp(S) * last  # (T, B, D, N)
            ys.append(torch.matmul(states, Ct[:, c]).squeeze(-1))  # (T, B, D)
            last = states[-1]
        y = torch.stack(ys, dim=1).view(size, chunks * batch, dim)
    y = _finish(_from_chunk_major(y, batch, length), u, D, z, dtype)
    return (y, last) if return_last_state else y


#: elements of one ``(T, chunks, B, D, N)`` buffer in :class:`SelectiveScanFn`'s backward (three are live at once)
BACKWARD_GROUP_ELEMENTS = 1 << 20


class SelectiveScanFn(torch.autograd.Function):
    """The chunked ``"steps"`` scan with a hand-written, memory-lean backward (recompute + adjoint by chunks).

    Autograd through :func:`selective_scan_chunked` (or the reference) keeps every step's ``(B, D, N)``
    intermediates -- several ``B x L x D x N`` tensors per scan until the backward pass. This Function runs the
    chunked scan without autograd and keeps only its inputs and the ``(K, B, D, N)`` states entering the ``K``
    chunks. The backward pass runs the adjoint recurrence of the scan in reverse time (per batch element, channel
    ``d``, state ``n``; ``g`` the gradient of ``y`` after the gate)::

        lam_t = C_t g_t + dA_{t+1} lam_{t+1}        (lam_{L+1} = 0; the gradient reaching h_t)
        grad dA_t = lam_t h_{t-1},  grad dBu_t = lam_t

    chained to ``delta`` (``d dA_t / d delta_t = A dA_t``, ``dBu_t = delta_t u_t B_t``), ``A``, ``u``, ``B``
    and ``C`` (``grad C_t = sum_d g_t h_t``), and the skip ``D`` and gate ``z`` directly. Like the forward it
    works by chunks: pass A runs every chunk's adjoint from a zero end state at once (``T`` steps over all
    chunks) and carries the adjoints from chunk to chunk back in time (a chunk passes ``decay_c`` of what enters
    its end on to its start); pass B then takes groups of chunks (``BACKWARD_GROUP_ELEMENTS`` per buffer),
    recomputes their ``T`` states from the saved chunk starts, runs their adjoints from the carried ones, and
    reduces the gradients over the group in batched products. Peak extra memory: ``O(B L (D + N) + B K D N)``
    plus three group buffers, instead of ``O(k B L D N)``. Once differentiable (no double backward).

    ``apply(u, delta, A, B, C, D, z, chunk_size, group_elements)`` -> ``(y (B, L, D) in u's dtype, last state
    (B, D, N))``; use :func:`selective_scan_lean`.
    """

    @staticmethod
    def forward(ctx, u, delta, A, B, C, D, z, chunk_size, group_elements):
        dtype, work = u.dtype, _work_dtype(u.dtype)
        uw, dw, Aw, Bw, Cw = (t.to(work) for t in (u, delta, A, B, C))
        batch, length, _ = u.shape
        size, chunks = _geometry(length, chunk_size)
        dt, xt = (_chunk_major(x, chunks, size).unsqueeze(-1) for x in (dw, dw * uw))
        Bt, Ct = _chunk_major(Bw, chunks, size).unsqueeze(2), _chunk_major(Cw, chunks, size).unsqueeze(-1)
        y, starts, last = _scan_steps(dt, xt, Bt, Ct, Aw, batch, in_place=True)
        y = _finish(_from_chunk_major(y, batch, length), uw, D, z, dtype)
        ctx.save_for_backward(u, delta, A, B, C, D, z, starts)
        ctx.geometry = (size, chunks, group_elements)
        ctx.set_materialize_grads(False)
        return y, last

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_out, g_last):
        u, delta, A, B, C, D, z, starts = ctx.saved_tensors
        n_inputs = (u, delta, A, B, C, D, z)
        if g_out is None and g_last is None:
            return (None,) * 9
        size, chunks, group_elements = ctx.geometry
        work = _work_dtype(u.dtype)
        uw, dw, Aw, Bw, Cw = (t.to(work) for t in (u, delta, A, B, C))
        batch, length, dim = u.shape
        n = A.shape[1]
        g_out = uw.new_zeros(uw.shape) if g_out is None else g_out.to(work)
        g_z = g_D = None
        if z is not None:
            gate_sig = torch.sigmoid(z.to(work))
            g_y = g_out * (z.to(work) * gate_sig)
        else:
            g_y = g_out
        if D is not None:
            g_D = (g_y * uw).sum((0, 1))
        A2 = Aw * math.log2(math.e)
        dt, ut, xt, gt = (_chunk_major(x, chunks, size) for x in (dw, uw, dw * uw, g_y))  # (T, M, D)
        Bt, Ct = _chunk_major(Bw, chunks, size), _chunk_major(Cw, chunks, size)  # (T, M, N)
        rows = chunks * batch
        # pass A: every chunk's adjoint from a zero end state, back to its start (times that step's dA)
        if chunks > 1:
            m = uw.new_zeros(rows, dim, n)
            for t in range(size - 1, -1, -1):
                m = torch.baddbmm(m, gt[t].unsqueeze(-1), Ct[t].unsqueeze(1)).mul_((dt[t].unsqueeze(-1) * A2).exp2_())
            decay = torch.exp(dt.sum(0).unsqueeze(-1) * Aw)  # (M, D, N)
            shape = (chunks, batch, dim, n)
            init = None if g_last is None else g_last.to(work)
            ends, _ = _carry(m.view(shape), decay.view(shape), init=init, reverse=True)
        else:
            ends = (uw.new_zeros(batch, dim, n) if g_last is None else g_last.to(work)).unsqueeze(0)
        ends = ends.reshape(rows, dim, n)  # the adjoint entering each chunk from its end (from later chunks)
        starts = starts.reshape(rows, dim, n)
        # pass B: by groups of chunks, recompute the states, run the adjoint, reduce the gradients
        g_delta, g_u, y_state = torch.empty_like(dt), torch.empty_like(dt), torch.empty_like(dt)
        g_B, g_C = torch.empty_like(Bt), torch.empty_like(Ct)
        g_A = torch.zeros_like(Aw)
        group = max(1, group_elements // (size * batch * dim * n)) * batch  # rows per group: whole chunks
        for r0 in range(0, rows, group):
            rs = slice(r0, min(r0 + group, rows))
            dg, ug, xg, gg, Bg, Cg = (x[:, rs] for x in (dt, ut, xt, gt, Bt, Ct))
            rows_g = dg.shape[1]
            hs = uw.new_empty(size + 1, rows_g, dim, n)  # hs[t + 1] = h_t; hs[0] = the chunks' start states
            dA_lam = uw.new_empty(size, rows_g, dim, n)  # dA_t, then lam_t * dA_t, then lam_t * dA_t * h_{t-1}
            lam = uw.new_empty(size, rows_g, dim, n)
            hs[0] = starts[rs]
            for t in range(size):
                torch.exp2(dg[t].unsqueeze(-1) * A2, out=dA_lam[t])
                torch.mul(dA_lam[t], hs[t], out=hs[t + 1]).addcmul_(xg[t].unsqueeze(-1), Bg[t].unsqueeze(1))
            m = ends[rs]
            for t in range(size - 1, -1, -1):
                torch.baddbmm(m, gg[t].unsqueeze(-1), Cg[t].unsqueeze(1), out=lam[t])
                m = dA_lam[t].mul_(lam[t])
            P = dA_lam.mul_(hs[:-1])  # grad of dA_t times dA_t
            g_A += torch.einsum("tmdn,tmd->dn", P, dg)
            lam_B = torch.matmul(lam, Bg.unsqueeze(-1)).squeeze(-1)  # (T, m, D): sum_n lam B
            g_delta[:, rs] = torch.einsum("tmdn,dn->tmd", P, Aw).addcmul_(lam_B, ug)
            g_u[:, rs] = lam_B * dg
            g_B[:, rs] = torch.matmul(xg.unsqueeze(2), lam).squeeze(2)  # sum_d lam delta u
            g_C[:, rs] = torch.matmul(gg.unsqueeze(2), hs[1:]).squeeze(2)  # sum_d g h
            if z is not None:
                y_state[:, rs] = torch.matmul(hs[1:], Cg.unsqueeze(-1)).squeeze(-1)
        g_delta, g_u, g_B, g_C = (_from_chunk_major(x, batch, length) for x in (g_delta, g_u, g_B, g_C))
        if D is not None:
            g_u = g_u.addcmul_(g_y, D.to(work))
        if z is not None:
            y = _from_chunk_major(y_state, batch, length)
            if D is not None:
                y = y.addcmul_(uw, D.to(work))
            zw = z.to(work)
            g_z = g_out * y * gate_sig * (1 + zw * (1 - gate_sig))  # silu'(z) = s (1 + z (1 - s))
        grads = (g_u, g_delta, g_A, g_B, g_C, g_D, g_z)
        grads = tuple(
            None if g is None or not need else g.to(x.dtype)
            for g, x, need in zip(grads, n_inputs, ctx.needs_input_grad[:7], strict=True)
        )
        return (*grads, None, None)


def selective_scan_lean(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    D: Tensor | None = None,
    z: Tensor | None = None,
    *,
    chunk_size: int = 64,
    return_last_state: bool = False,
    group_elements: int | None = None,
) -> Tensor | tuple[Tensor, Tensor]:
    """The chunked ``"steps"`` scan through :class:`SelectiveScanFn`: same result, memory-lean gradients.

    Same arguments and result as :func:`selective_scan_chunked`, plus ``group_elements`` (the backward's
    group buffer size, default ``BACKWARD_GROUP_ELEMENTS``). The last state is differentiable too.
    """
    _check(u, delta, A, B, C, D, z)
    _geometry(u.shape[1], chunk_size)
    group = BACKWARD_GROUP_ELEMENTS if group_elements is None else group_elements
    y, last = SelectiveScanFn.apply(u, delta, A, B, C, D, z, chunk_size, group)
    return (y, last) if return_last_state else y


@functools.lru_cache(maxsize=1)
def _mamba_ssm_kernel() -> Callable | None:
    """``mamba_ssm``'s ``selective_scan_fn``, or None when the package or its compiled kernel is missing.

    A ``mamba_ssm`` whose CUDA extension was not built (or was built for another torch) imports as a package but
    fails on ``selective_scan_cuda``: then ``"auto"`` warns once and keeps the chunked scan.
    """
    if importlib.util.find_spec("mamba_ssm") is None:
        return None
    try:
        from mamba_ssm.ops.selective_scan_interface import selective_scan_fn
    except (ImportError, OSError) as error:  # OSError: a kernel library built against another torch
        warnings.warn(
            f"mamba_ssm is installed but its scan kernel does not load ({error}); using the chunked scan", stacklevel=3
        )
        return None
    return selective_scan_fn


def _scan_mamba_ssm(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    D: Tensor | None,
    z: Tensor | None,
    return_last_state: bool,
    selective_scan_fn: Callable,
) -> Tensor | tuple[Tensor, Tensor]:
    def channels_first(x: Tensor | None) -> Tensor | None:
        return None if x is None else x.transpose(1, 2).contiguous()

    out = selective_scan_fn(
        channels_first(u),
        channels_first(delta),
        A.float().contiguous(),
        channels_first(B),
        channels_first(C),
        D=None if D is None else D.float(),
        z=channels_first(z),
        delta_bias=None,
        delta_softplus=False,
        return_last_state=return_last_state,
    )
    if return_last_state:
        y, last = out
        return y.transpose(1, 2), last
    return out.transpose(1, 2)


def selective_scan(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    D: Tensor | None = None,
    z: Tensor | None = None,
    *,
    mode: ScanMode = "auto",
    chunk_size: int = 64,
    return_last_state: bool = False,
) -> Tensor | tuple[Tensor, Tensor]:
    """Selective scan, dispatched: arguments and result as :func:`selective_scan_ref`.

    Args:
        mode: ``"ref"`` (the step loop), ``"chunked"`` (:func:`selective_scan_chunked`, ``"steps"``; when
            gradients are needed, :func:`selective_scan_lean`: the same forward, a memory-lean backward), or
            ``"auto"``: ``mamba_ssm``'s CUDA kernel when the tensors are CUDA float32/16/bfloat16 and
            ``mamba_ssm``'s kernel loads, else ``"chunked"``.
        chunk_size: ``T`` of the chunked scan.
    """
    if mode == "ref":
        return selective_scan_ref(u, delta, A, B, C, D, z, return_last_state=return_last_state)
    if mode not in ("auto", "chunked"):
        raise ValueError(f"selective scan: mode must be 'auto', 'chunked' or 'ref', got {mode!r}")
    if mode == "auto" and u.is_cuda and u.dtype in (torch.float32, torch.float16, torch.bfloat16):
        kernel = _mamba_ssm_kernel()
        if kernel is not None:
            _check(u, delta, A, B, C, D, z)
            return _scan_mamba_ssm(u, delta, A, B, C, D, z, return_last_state, kernel)
    if torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in (u, delta, A, B, C, D, z)):
        return selective_scan_lean(u, delta, A, B, C, D, z, chunk_size=chunk_size, return_last_state=return_last_state)
    return selective_scan_chunked(u, delta, A, B, C, D, z, chunk_size=chunk_size, return_last_state=return_last_state)


#: the CUDA path by public names, for a tool outside this sub-package (``occplug_occle.tools.bench`` times it)
mamba_ssm_kernel = _mamba_ssm_kernel
scan_mamba_ssm = _scan_mamba_ssm
