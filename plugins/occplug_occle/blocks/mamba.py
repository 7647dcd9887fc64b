"""OccLE's Dual Mamba (OccLE §3.4 and Appendix A): Mamba blocks over Hilbert-serialised feature grids.

OccLE fuses its semantic and geometric feature grids (spatially aligned, same ``(X, Y, Z)``) with a
U-Net of *dual* Mamba blocks: two parallel branches, one per grid, each adding a positional embedding,
then exchanging a subset of channels with the other branch, linearising its grid along a Hilbert curve
(:mod:`.serialization`), running a Mamba block (:class:`MambaBlock`, the selective scan of
:mod:`.selective_scan`) for long-range context at linear cost in ``X * Y * Z``, and restoring the grid.

Assumptions, where the paper is silent (OccLE §3.4, §4.1 and Appendix A / Fig. A1 are the whole description):

* **Channel exchange**: the paper says the branches "exchange subsets of their channels" (§3.4) / "exchange
  their feature channels" (App. A) without saying which. Here a fixed, evenly spread half: every other channel
  (the odd-indexed ones; :func:`exchange_mask`), in every block. Fixed, so applying it twice is the identity.
* **Positional embedding**: "compute positional embeddings for the two inputs" (App. A). Here a conditional
  positional encoding, ``x + DepthwiseConv3d_3x3x3(x)``, one per branch: it works for any grid shape and tells
  every token its 3D neighbourhood, which the 1D order loses where the curve folds.
* **Order of operations inside the block**: positional embedding -> exchange -> Hilbert order -> pre-norm
  Mamba with a residual (``s + Mamba(LayerNorm(s))``, the usual Mamba residual block) -> back to 3D. The
  residual adds the *exchanged* features, so the exchange persists in the output.
* **Mamba**: the original (Mamba-1, S6) mixer with its defaults (``d_state = 16``, ``d_conv = 4``,
  ``expand = 2``, ``dt_rank = ceil(C / 16)``), one direction along the curve, separate weights per branch.
* **U-Net**: "four downsampling stages and four upsampling stages. Each stage incorporates a dual Mamba
  block" (App. A), while §4.1 says "we stack 4 Dual Mamba blocks". We follow App. A: a block then a
  strided ``3x3x3`` convolution per down stage, an upsampling (trilinear to the skip's size, ``3x3x3``
  convolution), skip addition and a block per up stage, both branches kept apart throughout (each with its
  own skips) and joined only at the end by concatenation and a ``1x1x1`` convolution -- 8 blocks for 4
  stages. Down-sampling halves an axis only while it stays >= ``min_size`` (stride 1 after that), so
  ``32 x 32 x 4`` goes ``16 x 16 x 2``, ``8 x 8 x 2``, ``4 x 4 x 2``, ``2 x 2 x 2``. GroupNorm and SiLU
  after every down / up convolution (batch size 1 in the paper rules out BatchNorm).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
import torch.utils.checkpoint
from torch import Tensor, nn

from occplug.nn import ConvNormAct3d, halving_stride, norm_layer

from .selective_scan import ScanMode, selective_scan
from .serialization import deserialize, serialize

__all__ = ["DualMambaBlock", "DualMambaUNet", "MambaBlock", "channel_exchange", "exchange_mask"]


class MambaBlock(nn.Module):
    """The Mamba mixer (Gu & Dao 2023, Fig. 3): a gated selective-SSM block over a token sequence.

    ``in_proj`` -> ``x, z`` (``D = expand * dim`` each); ``x`` -> causal depthwise Conv1d -> SiLU ->
    the selective SSM, whose ``delta`` (low-rank ``dt_rank`` projection + softplus), ``B`` and ``C`` are
    projections of ``x`` itself -- different at every position, which is what makes the scan *selective* --
    with ``A = -exp(A_log)`` (S4D-real init ``A[d, n] = -(n + 1)``) and skip ``D``; the output is gated by
    ``silu(z)`` and projected back to ``dim``.

    Args:
        dim: ``C``, the token width.
        d_state: ``N``, SSM state size per channel.
        d_conv: kernel of the causal depthwise convolution.
        expand: ``D / C``.
        dt_rank: rank of the ``delta`` projection; None: ``ceil(dim / 16)``.
        dt_min, dt_max: range of the initial step sizes (log-uniform, through the ``dt_proj`` bias).
        scan: :func:`~.selective_scan.selective_scan` mode (``"auto"``: ``mamba_ssm`` on CUDA where its kernel loads,
            else the chunked scan).
        chunk_size: chunk length of the chunked scan.
        checkpoint_scan: in training, wrap the scan in ``torch.utils.checkpoint`` (recompute it in backward).
            Off by default: with gradients the pure-PyTorch scan already runs through
            :class:`~.selective_scan.SelectiveScanFn`, which keeps only its inputs and the chunk-start states and
            recomputes the rest by chunks in backward; checkpointing it on top only adds a second forward.
            Measured (CPU, one thread, ``DualMambaUNet(32, 32, channels=(32, 48, 64))`` forward + backward on
            ``(2, 32, 32, 32, 8)``): peak RSS ~630 MB / 2.5 s without, ~700 MB / 3.7 s with checkpointing; it was
            2679 MB / 4.3 s and 2121 MB / 4.9 s when autograd recorded every step of the scan.

    Forward: ``(B, L, C)`` -> ``(B, L, C)``; causal along ``L``.
    """

    def __init__(
        self,
        dim: int,
        d_state: int = 16,
        d_conv: int = 4,
        expand: int = 2,
        dt_rank: int | None = None,
        dt_min: float = 1e-3,
        dt_max: float = 0.1,
        scan: ScanMode = "auto",
        chunk_size: int = 64,
        checkpoint_scan: bool = False,
    ) -> None:
        super().__init__()
        inner = expand * dim
        self.d_state, self.scan, self.chunk_size = d_state, scan, chunk_size
        self.checkpoint_scan = checkpoint_scan
        self.dt_rank = math.ceil(dim / 16) if dt_rank is None else dt_rank
        self.in_proj = nn.Linear(dim, 2 * inner, bias=False)
        self.conv1d = nn.Conv1d(inner, inner, d_conv, groups=inner, padding=d_conv - 1)
        self.x_proj = nn.Linear(inner, self.dt_rank + 2 * d_state, bias=False)
        self.dt_proj = nn.Linear(self.dt_rank, inner)
        self.A_log = nn.Parameter(torch.log(torch.arange(1, d_state + 1, dtype=torch.float32)).repeat(inner, 1))
        self.D = nn.Parameter(torch.ones(inner))
        self.out_proj = nn.Linear(inner, dim, bias=False)
        with torch.no_grad():
            # Mamba's init: delta = softplus(bias) starts log-uniform in [dt_min, dt_max]
            bound = self.dt_rank**-0.5
            nn.init.uniform_(self.dt_proj.weight, -bound, bound)
            dt = torch.exp(torch.rand(inner) * (math.log(dt_max) - math.log(dt_min)) + math.log(dt_min))
            dt = dt.clamp(min=1e-4)
            self.dt_proj.bias.copy_(dt + torch.log(-torch.expm1(-dt)))  # inverse of softplus

    def selective_parameters(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The input-dependent SSM parameters for the (convolved, activated) inner sequence ``x`` ``(B, L, D)``.

        Returns:
            ``delta`` ``(B, L, D)`` (> 0), ``B`` ``(B, L, N)``, ``C`` ``(B, L, N)``.
        """
        dt, B, C = self.x_proj(x).split([self.dt_rank, self.d_state, self.d_state], dim=-1)
        return F.softplus(self.dt_proj(dt)), B, C

    def forward(self, tokens: Tensor) -> Tensor:
        length = tokens.shape[1]
        x, z = self.in_proj(tokens).chunk(2, dim=-1)  # (B, L, D) each
        x = F.silu(self.conv1d(x.transpose(1, 2))[..., :length].transpose(1, 2))  # causal: drop the look-ahead
        delta, B, C = self.selective_parameters(x)
        A = -torch.exp(self.A_log.float())
        args = (x, delta, A, B, C, self.D.float(), z)
        if self.checkpoint_scan and torch.is_grad_enabled() and x.requires_grad:
            y = torch.utils.checkpoint.checkpoint(self._scan, *args, use_reentrant=False)
        else:
            y = self._scan(*args)
        return self.out_proj(y)

    def _scan(self, x: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor, D: Tensor, z: Tensor) -> Tensor:
        return selective_scan(x, delta, A, B, C, D, z, mode=self.scan, chunk_size=self.chunk_size)


def exchange_mask(channels: int, ratio: float = 0.5) -> Tensor:
    """The channels that :func:`channel_exchange` swaps: ``floor(channels * ratio)`` of them, evenly spread.

    Channel ``c`` is swapped when ``floor((c + 1) * ratio) > floor(c * ratio)``: for ``ratio = 0.5`` every other
    channel (the odd-indexed ones), for ``0.25`` every fourth, for 1 all, for 0 none.

    Returns:
        ``(channels,)`` bool.
    """
    if not 0.0 <= ratio <= 1.0:
        raise ValueError(f"channel exchange: ratio must be in [0, 1], got {ratio}")
    c = torch.arange(channels + 1, dtype=torch.float64)
    steps = torch.floor(c * ratio)
    return steps[1:] > steps[:-1]


def channel_exchange(a: Tensor, b: Tensor, exchange: float | Tensor = 0.5, dim: int = 1) -> tuple[Tensor, Tensor]:
    """Swap a fixed subset of channels between two aligned feature tensors (OccLE's fusion step).

    Args:
        a, b: same shape, channels along ``dim`` (``(B, C, X, Y, Z)`` by default).
        exchange: the share of channels to swap (:func:`exchange_mask`; 0.5: every other channel), or a
            ``(C,)`` bool mask of the channels to swap.
        dim: the channel axis.

    Returns:
        ``(a', b')``: ``a'`` holds ``b``'s values in the swapped channels and ``a``'s elsewhere, and vice versa.
        An involution: exchanging ``(a', b')`` again gives back ``(a, b)``.
    """
    if a.shape != b.shape:
        raise ValueError(f"channel exchange: shapes differ, {tuple(a.shape)} vs {tuple(b.shape)}")
    channels = a.shape[dim]
    mask = exchange_mask(channels, exchange) if isinstance(exchange, float | int) else exchange
    if mask.shape != (channels,) or mask.dtype != torch.bool:
        raise ValueError(f"channel exchange: mask must be ({channels},) bool, got {tuple(mask.shape)} {mask.dtype}")
    view = [1] * a.dim()
    view[dim] = channels
    mask = mask.to(a.device).view(view)
    return torch.where(mask, b, a), torch.where(mask, a, b)


class DualMambaBlock(nn.Module):
    """One dual Mamba block (OccLE App. A): two aligned grids, positional embedding, channel exchange, Mamba.

    Per branch ``i`` (``a``: semantic, ``b``: geometric; the block is symmetric):
    ``x_i + PE_i(x_i)`` -> exchange channels with the other branch -> Hilbert order -> ``s + Mamba_i(LN_i(s))``
    -> back to the grid. See the module docstring for the assumptions.

    Args:
        channels: ``C`` of both grids.
        d_state, d_conv, expand: of the two :class:`MambaBlock` s.
        exchange_ratio: share of channels exchanged (every other channel at 0.5).
        scan, chunk_size: the selective scan's mode and chunk length.
        checkpoint: with gradients, run each branch's ``s + Mamba(LN(s))`` under ``torch.utils.checkpoint``
            (non-reentrant): the forward keeps only its input ``s`` ``(B, L, C)``, and the backward recomputes the
            Mamba mixer's activations, one branch at a time. Without it a branch keeps about 9 ``(B, L, D)``-sized
            tensors (``D = expand * C``: the input projection, the causal convolution's input and output, the
            ``x``-projection's input, the step sizes, the gate, the scan's inputs, the output projection's input)
            for backward; at the U-Net's first level (``L = X * Y * Z`` tokens) that is the largest share of a
            training step's memory. The same values and gradients (the mixer has no randomness), about one more
            forward of the mixers in time.

    Forward: ``(a (B, C, X, Y, Z), b (B, C, X, Y, Z))`` -> the same shapes, any ``(X, Y, Z)``.
    """

    def __init__(
        self,
        channels: int,
        d_state: int = 16,
        d_conv: int = 4,
        expand: int = 2,
        exchange_ratio: float = 0.5,
        scan: ScanMode = "auto",
        chunk_size: int = 64,
        checkpoint: bool = False,
    ) -> None:
        super().__init__()
        self.checkpoint = bool(checkpoint)
        self.pos_a = nn.Conv3d(channels, channels, 3, padding=1, groups=channels)
        self.pos_b = nn.Conv3d(channels, channels, 3, padding=1, groups=channels)
        self.norm_a, self.norm_b = nn.LayerNorm(channels), nn.LayerNorm(channels)
        mamba = {"d_state": d_state, "d_conv": d_conv, "expand": expand, "scan": scan, "chunk_size": chunk_size}
        self.mamba_a, self.mamba_b = MambaBlock(channels, **mamba), MambaBlock(channels, **mamba)
        self.register_buffer("exchange", exchange_mask(channels, exchange_ratio), persistent=False)

    def forward(self, a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
        shape = tuple(a.shape[2:])
        a, b = channel_exchange(a + self.pos_a(a), b + self.pos_b(b), self.exchange)
        sa, sb = serialize(a), serialize(b)  # (B, L, C) along the Hilbert curve
        sa = self._mix(self.norm_a, self.mamba_a, sa)
        sb = self._mix(self.norm_b, self.mamba_b, sb)
        return deserialize(sa, shape), deserialize(sb, shape)

    def _mix(self, norm: nn.LayerNorm, mamba: MambaBlock, s: Tensor) -> Tensor:
        """``s + mamba(norm(s))`` for ``s`` ``(B, L, C)``, recomputed in backward with ``checkpoint``."""
        if self.checkpoint and torch.is_grad_enabled():
            return torch.utils.checkpoint.checkpoint(_residual_mix, norm, mamba, s, use_reentrant=False)
        return _residual_mix(norm, mamba, s)


def _residual_mix(norm: nn.LayerNorm, mamba: MambaBlock, s: Tensor) -> Tensor:
    return s + mamba(norm(s))


class _Down(nn.Module):
    """``3x3x3`` convolution with stride 2 along the axes still >= ``2 * min_size`` long, 1 along the others."""

    def __init__(self, c_in: int, c_out: int, min_size: int) -> None:
        super().__init__()
        self.min_size = min_size
        self.conv = nn.Conv3d(c_in, c_out, 3, padding=1, bias=False)
        self.post = nn.Sequential(norm_layer("group", c_out, 3), nn.SiLU())

    def forward(self, x: Tensor) -> Tensor:
        stride = halving_stride(x.shape[2:], self.min_size)
        return self.post(F.conv3d(x, self.conv.weight, None, stride, 1))


class DualMambaUNet(nn.Module):
    """OccLE's Dual Mamba: a two-branch U-Net of :class:`DualMambaBlock` s fusing two aligned grids into one.

    Stage ``i`` of ``S = len(channels) - 1``: down -- a dual block at ``channels[i]``, then a strided
    convolution per branch to ``channels[i + 1]``; up (in reverse) -- upsample to the skip's size with a
    convolution to ``channels[i]``, add the branch's skip, a dual block. Last, the two branches are
    concatenated and a ``1x1x1`` convolution gives ``out_channels``. The module docstring lists the
    assumptions (paper: four stages, App. A).

    Args:
        in_channels: ``C_in`` of both grids, or ``(C_a, C_b)`` when they differ.
        out_channels: ``C_out`` of the fused grid.
        channels: widths per resolution level, ``S + 1`` of them (default: 4 stages).
        d_state, expand: of the Mamba blocks.
        exchange_ratio: share of channels exchanged in every dual block.
        min_size: an axis is halved only while it is >= ``2 * min_size`` (so ``Z = 4`` halves once).
        scan, chunk_size: the selective scan's mode and chunk length.
        checkpoint: every block's Mamba mixers recomputed in backward (:class:`DualMambaBlock`): the same values
            and gradients, less memory, more time. Off by default.

    Forward: ``(a (B, C_a, X, Y, Z), b (B, C_b, X, Y, Z))`` -> ``(B, C_out, X, Y, Z)``, any ``(X, Y, Z)``.
    """

    def __init__(
        self,
        in_channels: int | tuple[int, int],
        out_channels: int,
        channels: Sequence[int] = (16, 24, 32, 48, 64),
        d_state: int = 16,
        expand: int = 2,
        exchange_ratio: float = 0.5,
        min_size: int = 2,
        scan: ScanMode = "auto",
        chunk_size: int = 64,
        checkpoint: bool = False,
    ) -> None:
        super().__init__()
        if len(channels) < 2:
            raise ValueError(f"dual mamba u-net: need >= 2 channel widths (one stage), got {tuple(channels)}")
        c_a, c_b = (in_channels, in_channels) if isinstance(in_channels, int) else in_channels
        widths = list(channels)
        block = {
            "d_state": d_state,
            "expand": expand,
            "exchange_ratio": exchange_ratio,
            "scan": scan,
            "chunk_size": chunk_size,
            "checkpoint": checkpoint,
        }
        self.stem_a, self.stem_b = nn.Conv3d(c_a, widths[0], 1), nn.Conv3d(c_b, widths[0], 1)
        stages = range(len(widths) - 1)
        self.down_blocks = nn.ModuleList(DualMambaBlock(widths[i], **block) for i in stages)
        self.downs_a = nn.ModuleList(_Down(widths[i], widths[i + 1], min_size) for i in stages)
        self.downs_b = nn.ModuleList(_Down(widths[i], widths[i + 1], min_size) for i in stages)
        self.ups_a = nn.ModuleList(ConvNormAct3d(widths[i + 1], widths[i], norm="group", act="silu") for i in stages)
        self.ups_b = nn.ModuleList(ConvNormAct3d(widths[i + 1], widths[i], norm="group", act="silu") for i in stages)
        self.up_blocks = nn.ModuleList(DualMambaBlock(widths[i], **block) for i in stages)
        self.head = nn.Conv3d(2 * widths[0], out_channels, 1)

    def forward(self, a: Tensor, b: Tensor) -> Tensor:
        if a.shape[0] != b.shape[0] or a.shape[2:] != b.shape[2:]:
            raise ValueError(f"dual mamba u-net: grids not aligned, {tuple(a.shape)} vs {tuple(b.shape)}")
        a, b = self.stem_a(a), self.stem_b(b)
        skips = []
        for block, down_a, down_b in zip(self.down_blocks, self.downs_a, self.downs_b, strict=True):
            a, b = block(a, b)
            skips.append((a, b))
            a, b = down_a(a), down_b(b)
        for i in reversed(range(len(self.up_blocks))):
            skip_a, skip_b = skips[i]
            size = skip_a.shape[2:]
            a = skip_a + self.ups_a[i](F.interpolate(a, size=size, mode="trilinear", align_corners=False))
            b = skip_b + self.ups_b[i](F.interpolate(b, size=size, mode="trilinear", align_corners=False))
            a, b = self.up_blocks[i](a, b)
        return self.head(torch.cat([a, b], dim=1))
