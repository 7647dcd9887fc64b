"""The selective state-space scan of Mamba (S6; Gu & Dao 2023, Alg. 2), in pure PyTorch.

Per batch element, channel ``d`` and state ``n`` (zero initial state ``h_0 = 0``)::

    dA_t = exp(delta_t * A)               # discretised decay, in (0, 1] when delta >= 0 and A <= 0
    h_t  = dA_t * h_{t-1} + delta_t * B_t * u_t
    y_t  = sum_n C_t[n] * h_t[n] + D * u_t,  then  y_t * silu(z_t)  when a gate z is given

with ``delta``, ``B`` and ``C`` varying along the sequence -- that is what makes the scan *selective*.

Three implementations with one signature (sequence-major layout ``(B, L, ...)``):

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
* ``mamba_ssm``'s CUDA kernel ``selective_scan_fn``, used by :func:`selective_scan` in ``"auto"`` mode
  when the tensors are on CUDA, float32/16/bfloat16, and the ``mamba_ssm`` package is installed; it is
  never imported otherwise.

Measured with ``scripts/bench_occle.py`` (CPU, one thread of a shared machine, ``B = 2, L = 4096, D = 64,
N = 16``, forward without autograd, median of 5): ref 264 ms vs ``"steps"`` (``T = 64``) 37 ms in float32
(7.2x); 386 ms vs 65 ms in float64 (5.9x); ``"segsum"`` (``T = 8``, float64) 526 ms (0.7x). The
reference's time is mostly its ``L`` Python iterations (its ``einsum`` per step alone is about half).
"""

from __future__ import annotations

import functools
import importlib.util
import math
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["ScanMode", "selective_scan", "selective_scan_chunked", "selective_scan_ref"]

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


def _carry(local_last: Tensor, decay: Tensor) -> tuple[Tensor, Tensor]:
    """States entering each chunk: ``start_{c+1} = decay_c * start_c + local_last_c``, ``start_0 = 0``.

    Args:
        local_last: ``(B, K, D, N)`` each chunk's last state from a zero start.
        decay: ``(B, K, D, N)`` each chunk's total decay ``exp(A * sum delta)`` in (0, 1].

    Returns:
        ``(starts (B, K, D, N), final (B, D, N))``.
    """
    state = torch.zeros_like(local_last[:, 0])
    starts = []
    for c in range(local_last.shape[1]):
        starts.append(state)
        state = torch.addcmul(local_last[:, c], decay[:, c], state)
    return torch.stack(starts, dim=1), state


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
    if chunk_size < 1:
        raise ValueError(f"selective scan: chunk_size must be >= 1, got {chunk_size}")
    if within_chunk not in ("steps", "segsum"):
        raise ValueError(f"selective scan: within_chunk must be 'steps' or 'segsum', got {within_chunk!r}")
    dtype, work = u.dtype, _work_dtype(u.dtype)
    u, delta, A, B, C = (t.to(work) for t in (u, delta, A, B, C))
    batch, length, dim = u.shape
    n = A.shape[1]
    size = min(chunk_size, length)
    chunks = math.ceil(length / size)
    pad = chunks * size - length

    def time_major(x: Tensor) -> Tensor:
        # (B, L, K) -> (T, B * chunks, K): step t of every chunk is one contiguous slice
        x = F.pad(x, (0, 0, 0, pad))
        return x.view(batch, chunks, size, -1).permute(2, 0, 1, 3).reshape(size, batch * chunks, -1)

    dt, xt = time_major(delta).unsqueeze(-1), time_major(delta * u).unsqueeze(-1)  # (T, M, D, 1), M = B * chunks
    Bt, Ct = time_major(B).unsqueeze(2), time_major(C).unsqueeze(-1)  # (T, M, 1, N), (T, M, N, 1)
    if within_chunk == "steps":
        # dA and dBu are formed step by step (twice) rather than stored: a (T, M, D, N) tensor is fresh memory
        # on every call, and filling it costs more than recomputing the exponentials. Without autograd each
        # step allocates one (M, D, N) tensor and works in place on it: fewer fresh pages per step.
        in_place = not (torch.is_grad_enabled() and any(t.requires_grad for t in (u, delta, A, B, C)))
        A2 = A * math.log2(math.e)
        h = xt.new_zeros(batch * chunks, dim, n)
        if chunks > 1:
            for t in range(size):  # pass 1: each chunk's own last state, from zero
                h = _step(h, dt[t], xt[t], Bt[t], A2, in_place)
            decay = torch.exp(dt.sum(0) * A)  # (M, D, N): the chunk's log-space sum, <= 0
            starts, last = _carry(h.view(batch, chunks, dim, n), decay.view(batch, chunks, dim, n))
            h = starts.reshape(batch * chunks, dim, n)
        ys = []
        for t in range(size):  # pass 2: the same steps from the carried states
            h = _step(h, dt[t], xt[t], Bt[t], A2, in_place)
            ys.append(torch.bmm(h, Ct[t]).squeeze(-1))
        y = torch.stack(ys)  # (T, M, D)
        if chunks == 1:
            last = h
    else:
        dt, xt = dt.view(size, batch, chunks, dim, 1), xt.view(size, batch, chunks, dim, 1)
        Bt, Ct = Bt.view(size, batch, chunks, 1, n), Ct.view(size, batch, chunks, n, 1)
        above = ~torch.ones(size, size, dtype=torch.bool, device=u.device).tril().view(size, size, 1, 1, 1)
        last = xt.new_zeros(batch, dim, n)
        ys = []
        for c in range(chunks):
            S = torch.cumsum(dt[:, :, c] * A, dim=0)  # (T, B, D, N): log-space cumsum of log dA within the chunk
            # weights[t, s] = exp(S_t - S_s) = prod_{s < r <= t} dA_r for s <= t (exponent <= 0); 0 above
            weights = (S.unsqueeze(1) - S.unsqueeze(0)).masked_fill(above, float("-inf")).exp()
            dBu = xt[:, :, c] * Bt[:, :, c]  # (T, B, D, N)
            states = (weights * dBu.unsqueeze(0)).sum(1) + torch.exp(S) * last  # (T, B, D, N)
            ys.append(torch.matmul(states, Ct[:, :, c]).squeeze(-1))  # (T, B, D)
            last = states[-1]
        y = torch.stack(ys, dim=2).view(size, batch * chunks, dim)
    y = y.view(size, batch, chunks, dim).permute(1, 2, 0, 3).reshape(batch, chunks * size, dim)[:, :length]
    y = _finish(y, u, D, z, dtype)
    return (y, last) if return_last_state else y


@functools.lru_cache(maxsize=1)
def _mamba_ssm_installed() -> bool:
    return importlib.util.find_spec("mamba_ssm") is not None


def _scan_mamba_ssm(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    D: Tensor | None,
    z: Tensor | None,
    return_last_state: bool,
) -> Tensor | tuple[Tensor, Tensor]:
    from mamba_ssm.ops.selective_scan_interface import selective_scan_fn

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
        mode: ``"ref"`` (the step loop), ``"chunked"`` (:func:`selective_scan_chunked`, ``"steps"``), or
            ``"auto"``: ``mamba_ssm``'s CUDA kernel when the tensors are CUDA float32/16/bfloat16 and
            ``mamba_ssm`` is installed, else ``"chunked"``.
        chunk_size: ``T`` of the chunked scan.
    """
    if mode == "ref":
        return selective_scan_ref(u, delta, A, B, C, D, z, return_last_state=return_last_state)
    if mode not in ("auto", "chunked"):
        raise ValueError(f"selective scan: mode must be 'auto', 'chunked' or 'ref', got {mode!r}")
    if (
        mode == "auto"
        and u.is_cuda
        and u.dtype in (torch.float32, torch.float16, torch.bfloat16)
        and _mamba_ssm_installed()
    ):
        _check(u, delta, A, B, C, D, z)
        return _scan_mamba_ssm(u, delta, A, B, C, D, z, return_last_state)
    return selective_scan_chunked(u, delta, A, B, C, D, z, chunk_size=chunk_size, return_last_state=return_last_state)
