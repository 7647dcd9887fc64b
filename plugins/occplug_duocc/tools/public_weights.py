"""The public DuOcc code's modules as occplug's: their sizes in the parity fixtures, layouts and weight mapping.

This is occplug-side knowledge of the public code's parameter names and tensor layouts (read from its configuration
and module definitions): :mod:`.public_parity` builds the public modules beside occplug's and writes what they
compute into ``tests/fixtures/public_parity/``; the parity tests map the stored public weights with the functions
here and run occplug's modules, with no public code at hand.

Layouts (the code's; ours are ``(B, C, X, Y, Z)`` volumes, ego frame, yaw boxes):

* StreamAgg volumes are ``(B, C, Z, Y, X)`` (its LSS layout): :func:`from_zyx`;
* DQA / V2Q volumes are ``(B, Y, X, Z, C)`` (flat voxel index ``(y * X + x) * Z + z``): :func:`from_yxzc`;
* boxes are encoded ``[x, y, z, log l, log w, log h, sin, cos, vx, vy, vz]`` with a raw ``(sin, cos)``:
  :func:`sin_cos_boxes` turns them into the ``box_rotation="sin_cos"`` layout ``[x, y, z, l, w, h, sin, cos]``;
* a 3D convolution kernel follows its volume's axes: :func:`kernel_from_zyx`, :func:`kernel_from_yxz`;
* a convolution bias right before an inference-mode BatchNorm folds into its running mean.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import Tensor

__all__ = [
    "DQA_SPEC",
    "STREAM_SPEC",
    "V2Q_SPEC",
    "from_yxzc",
    "from_zyx",
    "kernel_from_yxz",
    "kernel_from_zyx",
    "map_decoder",
    "map_dqa",
    "map_forecast",
    "map_fusion",
    "map_occupied",
    "map_refinenet",
    "map_stream_agg",
    "map_v2q",
    "max_relative_difference",
    "sin_cos_boxes",
]

#: DQA (with the FFN and the closing LayerNorm of the code's cross-attention layer) and the occupancy decoder:
#: ``C`` channels, ``heads``, ``K`` classes, the ``{range, voxel_size}`` grid (square in x / y as the code needs).
DQA_SPEC = {"channels": 16, "heads": 4, "num_classes": 5, "range": (-4.0, -4.0, -2.0, 4.0, 4.0, 2.0), "voxel": 1.0}
#: V2Q: ``channels``, ``heads`` (the code's groups) x ``points`` per head, the grid.
V2Q_SPEC = {"channels": 16, "heads": 4, "points": 3, "range": (-4.0, -4.0, -2.0, 4.0, 4.0, 2.0), "voxel": 1.0}
#: StreamAgg's RefineNet, occupied / forecast heads and fusion: ``channels`` (internal ``channels // 4``).
STREAM_SPEC = {"channels": 32, "num_classes": 5, "range": (-4.0, -4.0, -2.0, 4.0, 4.0, 2.0), "voxel": 1.0}


def max_relative_difference(ours: Tensor, public: Tensor) -> float:
    """``max |ours - public| / max |public|`` (float64)."""
    ours, public = ours.detach().double(), public.detach().double()
    if ours.shape != public.shape:
        raise ValueError(f"max_relative_difference: shapes {tuple(ours.shape)} and {tuple(public.shape)} differ")
    return float((ours - public).abs().max() / public.abs().max().clamp(min=1e-30))


def from_zyx(volume: Tensor) -> Tensor:
    """``(B, C, Z, Y, X)`` -> ``(B, C, X, Y, Z)`` (the code's StreamAgg layout)."""
    return volume.permute(0, 1, 4, 3, 2)


def from_yxzc(volume: Tensor) -> Tensor:
    """``(B, Y, X, Z, C)`` -> ``(B, C, X, Y, Z)`` (the code's DQA / V2Q layout)."""
    return volume.permute(0, 4, 2, 1, 3)


def kernel_from_zyx(weight: Tensor) -> Tensor:
    """A conv kernel ``(O, I, kz, ky, kx)`` (or a transposed conv's ``(I, O, ...)``) -> ``(O, I, kx, ky, kz)``."""
    return weight.permute(0, 1, 4, 3, 2)


def kernel_from_yxz(weight: Tensor) -> Tensor:
    """A conv kernel ``(O, I, ky, kx, kz)`` -> ``(O, I, kx, ky, kz)``."""
    return weight.permute(0, 1, 3, 2, 4)


def sin_cos_boxes(encoded: Tensor) -> Tensor:
    """``(..., >=8)`` encoded boxes ``[x, y, z, log l, log w, log h, sin, cos, ...]`` -> ``(..., 8)``
    ``[x, y, z, l, w, h, sin, cos]`` (the raw pair kept: ``box_rotation="sin_cos"``)."""
    return torch.cat([encoded[..., :3], encoded[..., 3:6].exp(), encoded[..., 6:8]], -1)


def _bn(sd: Mapping[str, Tensor], src: str, dst: str, conv_bias: Tensor | None = None) -> dict[str, Tensor]:
    """A BatchNorm's state; a preceding conv's bias folds into the running mean (inference-mode only)."""
    out = {f"{dst}.{k}": sd[f"{src}.{k}"] for k in ("weight", "bias", "running_mean", "running_var")}
    out[f"{dst}.num_batches_tracked"] = sd[f"{src}.num_batches_tracked"]
    if conv_bias is not None:  # BN(y + b) = gamma (y - (mu - b)) / sigma + beta
        out[f"{dst}.running_mean"] = out[f"{dst}.running_mean"] - conv_bias
    return out


def map_dqa(sd: Mapping[str, Tensor], pos: Mapping[str, Tensor]) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
    """The code's ``DQA`` (``query_to_vox``, no occupancy head) and its learned positional encoding -> the state
    dicts of :class:`~occplug_duocc.blocks.dqa.DynamicQueryAggregation` (``output_bias``, ``instance_norm``,
    ``positional_order="yxz"``) and of the :class:`~occplug_duocc.blocks.dqa.VoxelFFN` after it.

    The code's gate ``sigmoid(W_ih z + W_hh V)`` is ``W_gate [V, z]``: its weight is ``[W_hh | W_ih]``, its bias
    the sum of both. Its positional tables are ``row`` (y), ``col`` (x), ``tub`` (z); ours are per axis x, y, z.
    """
    a = "cross_attn_Q2V"
    dqa = {
        "w_q.weight": sd[f"{a}.lin_q_node.weight"],
        "w_q.bias": sd[f"{a}.lin_q_node.bias"],
        "w_k.weight": sd[f"{a}.lin_k_node.weight"],
        "w_k.bias": sd[f"{a}.lin_k_node.bias"],
        "w_v.weight": sd[f"{a}.lin_v_node.weight"],
        "w_v.bias": sd[f"{a}.lin_v_node.bias"],
        "w_gate.weight": torch.cat([sd[f"{a}.lin_hh.weight"], sd[f"{a}.lin_ih.weight"]], 1),
        "w_gate.bias": sd[f"{a}.lin_ih.bias"] + sd[f"{a}.lin_hh.bias"],
        "w_out.weight": sd[f"{a}.out_proj.weight"],
        "w_out.bias": sd[f"{a}.out_proj.bias"],
        "instance_norm.weight": sd[f"{a}.norm1.weight"],
        "instance_norm.bias": sd[f"{a}.norm1.bias"],
        "pos.0": pos["col_embed.weight"],
        "pos.1": pos["row_embed.weight"],
        "pos.2": pos["tub_embed.weight"],
    }
    ffn = {
        "norm.weight": sd[f"{a}.norm3.weight"],
        "norm.bias": sd[f"{a}.norm3.bias"],
        "mlp.0.weight": sd[f"{a}.mlp.0.weight"],
        "mlp.0.bias": sd[f"{a}.mlp.0.bias"],
        "mlp.2.weight": sd[f"{a}.mlp.3.weight"],
        "mlp.2.bias": sd[f"{a}.mlp.3.bias"],
        "final.weight": sd["norm_cross.weight"],
        "final.bias": sd["norm_cross.bias"],
    }
    return dqa, ffn


def map_decoder(sd: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """The code's DQA occupancy head (``up_block``, ``proj_layer``, ``vox_occ_net``) ->
    :class:`~occplug_duocc.heads.DuOccDecoder` (``hidden = C / 4``, ``mlp_hidden = C``); its kernels are (y, x, z)."""
    out = {"up.0.weight": kernel_from_yxz(sd["up_block.0.weight"])}
    out.update(_bn(sd, "up_block.1", "up.1", conv_bias=sd["up_block.0.bias"]))
    w = sd["proj_layer.conv.weight"]
    out["mlp.0.weight"], out["mlp.0.bias"] = w.view(w.shape[0], w.shape[1]), sd["proj_layer.conv.bias"]
    w = sd["vox_occ_net.weight"]
    out["mlp.2.weight"], out["mlp.2.bias"] = w.view(w.shape[0], w.shape[1]), sd["vox_occ_net.bias"]
    return out


def map_v2q(sd: Mapping[str, Tensor], heads: int, points: int) -> dict[str, Tensor]:
    """The code's ``DeformableFeatureAggregation`` on voxels (its ``deformable_model_vox``) ->
    :class:`~occplug_duocc.blocks.v2q.VoxelToQuery` (``value_bias``, ``fixed_key_points``).

    The code's weight Linear is laid out point-major (row ``o * heads + h``), ours head-major (``h * points + o``);
    its key points are head-major as ours (point ``p`` of head ``p // points``).
    """
    src = (torch.arange(points)[None, :] * heads + torch.arange(heads)[:, None]).flatten()  # our row h * O + o
    return {
        "offsets.weight": sd["kps_generator.learnable_fc.weight"],
        "offsets.bias": sd["kps_generator.learnable_fc.bias"],
        "attn.weight": sd["voxel_weights_fc.weight"][src],
        "attn.bias": sd["voxel_weights_fc.bias"][src],
        "value_proj.weight": sd["DA3D.value_proj.weight"],
        "value_bias": sd["DA3D.value_proj.bias"],
        "out_proj.weight": sd["DA3D.output_proj.weight"],
        "out_proj.bias": sd["DA3D.output_proj.bias"],
    }


def map_refinenet(sd: Mapping[str, Tensor], prefix: str = "") -> dict[str, Tensor]:
    """The code's ``RefineNet`` (biased convolutions, CBAM ``fc1`` / ``fc2`` / spatial conv) ->
    :class:`~occplug_duocc.blocks.stream_agg.RefineNet` (``residual_relu=True``); kernels are (z, y, x)."""
    p = prefix
    out: dict[str, Tensor] = {}
    for i, (conv, bn) in enumerate((("conv1", "bn1"), ("conv2", "bn2"), ("conv3", "bn3"))):
        out[f"bottleneck.{3 * i}.weight"] = kernel_from_zyx(sd[f"{p}{conv}.weight"])
        out.update(_bn(sd, f"{p}{bn}", f"bottleneck.{3 * i + 1}", conv_bias=sd[f"{p}{conv}.bias"]))
    out["channel_mlp.0.weight"] = sd[f"{p}cbam.channel_attention.fc1.weight"]
    out["channel_mlp.2.weight"] = sd[f"{p}cbam.channel_attention.fc2.weight"]
    out["spatial_conv.weight"] = kernel_from_zyx(sd[f"{p}cbam.spatial_attention.conv.weight"])
    return out


def map_occupied(sd: Mapping[str, Tensor], prefix: str = "") -> dict[str, Tensor]:
    """The code's occupied-mask head inside RefineNet (``up_block``, bias-free ``pred_occ_mask``) ->
    :class:`~occplug_duocc.blocks.stream_agg.UpsampleDecoder` ``(1, C / 4, 1)``; it ends in a sigmoid, ours in the
    logit."""
    p = prefix
    out = {"net.0.weight": kernel_from_zyx(sd[f"{p}up_block.0.weight"])}
    out.update(_bn(sd, f"{p}up_block.1", "net.1"))
    out["net.3.weight"] = sd[f"{p}pred_occ_mask.weight"]
    out["net.3.bias"] = torch.zeros(1, dtype=out["net.3.weight"].dtype)
    return out


def map_forecast(sd: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """The code's StreamAgg forecast head (``pred_up_block``, bias-free ``forecast_occ_net``) ->
    :class:`~occplug_duocc.blocks.stream_agg.UpsampleDecoder` ``(C, C, K)``."""
    out = {"net.0.weight": kernel_from_zyx(sd["pred_up_block.0.weight"])}
    out.update(_bn(sd, "pred_up_block.1", "net.1"))
    w = sd["forecast_occ_net.weight"]
    out["net.3.weight"] = w
    out["net.3.bias"] = torch.zeros(w.shape[0], dtype=w.dtype)
    return out


def map_fusion(sd: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """The code's ``cat_block`` (bias-free 1x1x1 conv on ``[refined, current]``, GroupNorm, ReLU) -> StreamAgg's
    ``fuse``."""
    return {
        "0.weight": sd["cat_block.0.weight"],
        "1.weight": sd["cat_block.1.weight"],
        "1.bias": sd["cat_block.1.bias"],
    }


def map_stream_agg(sd: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """The code's whole ``StreamAgg`` (RefineNet with the occupied head, forecast head, concat fusion) ->
    :class:`~occplug_duocc.blocks.stream_agg.StreamAggregation` (``fusion="concat"``, ``residual_relu=True``)."""
    out = {f"refine.{k}": v for k, v in map_refinenet(sd, "temporal_conv_net.").items()}
    out.update({f"occupied.{k}": v for k, v in map_occupied(sd, "temporal_conv_net.").items()})
    out.update({f"forecast.{k}": v for k, v in map_forecast(sd).items()})
    out.update({f"fuse.{k}": v for k, v in map_fusion(sd).items()})
    return out
