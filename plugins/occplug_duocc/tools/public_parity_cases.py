"""occplug's side of the public-code parity fixtures: each module under the ``duocc/code_recipe`` switches, run on a
fixture's mapped weights and inputs, against the public outputs it stores.

A fixture (``tests/fixtures/public_parity/<module>.pt``, written by :mod:`.public_parity`) holds ``inputs``,
``public_state_dict`` and ``public_outputs``, in the public code's layouts (:mod:`.public_weights`). Each case here
maps them, runs occplug's module in inference mode and returns ``{output: max relative difference}``
(:func:`~.public_weights.max_relative_difference`); the parity tests assert each is at most ``1e-5``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from occplug.geometry import GridSpec

from ..blocks.dqa import DynamicQueryAggregation, VoxelFFN
from ..blocks.stream_agg import RefineNet, StreamAggregation, UpsampleDecoder
from ..blocks.v2q import VoxelToQuery
from ..heads import DuOccDecoder
from .class_weights import duocc_class_weights
from .public_weights import (
    DQA_SPEC,
    STREAM_SPEC,
    V2Q_SPEC,
    from_yxzc,
    from_zyx,
    map_decoder,
    map_dqa,
    map_forecast,
    map_fusion,
    map_occupied,
    map_refinenet,
    map_stream_agg,
    map_v2q,
    max_relative_difference,
    sin_cos_boxes,
)

__all__ = ["CASES", "FIXTURE_DIR", "FIXTURE_OF"]

#: Where the fixtures live (in the plugin's tests).
FIXTURE_DIR = Path(__file__).resolve().parent.parent / "tests" / "fixtures" / "public_parity"


def _grid(spec: dict) -> GridSpec:
    return GridSpec(spec["range"], spec["voxel"])


def _load(module: torch.nn.Module, state: dict[str, Tensor]) -> torch.nn.Module:
    module.load_state_dict(state, strict=True)
    return module.eval()


def dqa(fx: dict[str, Any]) -> dict[str, float]:
    """The code's DQA (cross-attention, FFN, closing LayerNorm) = occplug's DQA then :class:`VoxelFFN`."""
    spec, inp = DQA_SPEC, fx["inputs"]
    sd = fx["public_state_dict"]
    c = spec["channels"]
    dqa_sd, ffn_sd = map_dqa(sd, {k[4:]: v for k, v in sd.items() if k.startswith("pos.")})
    attn = DynamicQueryAggregation(
        c,
        _grid(spec),
        heads=spec["heads"],
        coverage="aabb",
        output_bias=True,
        instance_norm=True,
        outside_boxes="clamp",
        empty_selection="dummy_query",
        box_rotation="sin_cos",
        positional_order="yxz",
    )
    ffn = VoxelFFN(c)
    _load(attn, dqa_sd), _load(ffn, ffn_sd)
    with torch.no_grad():
        volume = from_yxzc(inp["volume"])
        out = ffn(attn(volume, inp["queries"], sin_cos_boxes(inp["boxes"]), inp["selected"]))
    return {"volume": max_relative_difference(out, from_yxzc(fx["public_outputs"]["volume"]))}


def decoder(fx: dict[str, Any]) -> dict[str, float]:
    """The code's occupancy head (inside its DQA) = :class:`DuOccDecoder` (``hidden = C / 4``, ``mlp_hidden = C``)."""
    from occplug.interfaces import DenseVoxelScene

    spec = DQA_SPEC
    c = spec["channels"]
    label_grid = GridSpec(spec["range"], spec["voxel"] / 2)  # the decoder upsamples the scene's grid by 2
    head = _load(
        DuOccDecoder(c, label_grid, 2, spec["num_classes"], hidden=c // 4, mlp_hidden=c),
        map_decoder(fx["public_state_dict"]),
    )
    with torch.no_grad():
        logits = head(DenseVoxelScene(from_yxzc(fx["inputs"]["volume"]), _grid(spec)), None)["logits"]
    return {"logits": max_relative_difference(logits, fx["public_outputs"]["logits"])}  # the code's is (B, K, X, Y, Z)


def v2q(fx: dict[str, Any]) -> dict[str, float]:
    """The code's voxel deformable aggregation = :class:`VoxelToQuery` under the code's switches."""
    spec, inp = V2Q_SPEC, fx["inputs"]
    heads, points = spec["heads"], spec["points"]
    block = VoxelToQuery(
        spec["channels"],
        _grid(spec),
        heads=heads,
        points=points,
        dropout=0.0,
        offset_input="feature",
        value_bias=True,
        fixed_key_points=True,
        box_rotation="sin_cos",
    )
    _load(block, map_v2q(fx["public_state_dict"], heads, points))
    with torch.no_grad():
        out = block(from_yxzc(inp["volume"]), inp["queries"], sin_cos_boxes(inp["boxes"]), inp["anchor_embed"])
    return {"queries": max_relative_difference(out, fx["public_outputs"]["queries"])}


def _refinenet(fx: dict[str, Any]) -> tuple[Tensor, Tensor]:
    c = STREAM_SPEC["channels"]
    sd = fx["public_state_dict"]
    net = _load(RefineNet(c, reduction=16, residual_relu=True), map_refinenet(sd))
    occupied = _load(UpsampleDecoder(1, c // 4, 1, 2), map_occupied(sd))
    with torch.no_grad():
        refined, attention = net(from_zyx(fx["inputs"]["volume"]))
        return refined, occupied(attention.spatial_logits).sigmoid()


def refinenet(fx: dict[str, Any]) -> dict[str, float]:
    """The code's RefineNet (its residual ReLU on) = :class:`RefineNet` with ``residual_relu=True``."""
    refined, _ = _refinenet(fx)
    return {"refined": max_relative_difference(refined, from_zyx(fx["public_outputs"]["refined"]))}


def occupied_head(fx: dict[str, Any]) -> dict[str, float]:
    """The code's occupied-mask head (a sigmoid at its end) = sigmoid of :class:`UpsampleDecoder` on ``M_s``."""
    _, occupied = _refinenet(fx)
    return {"occupied": max_relative_difference(occupied, from_zyx(fx["public_outputs"]["occupied"]))}


def fusion(fx: dict[str, Any]) -> dict[str, float]:
    """The code's ``cat_block`` = StreamAgg's ``fusion="concat"``."""
    spec = STREAM_SPEC
    agg = StreamAggregation(
        spec["channels"], spec["num_classes"], _grid(spec), fusion="concat", occupied_head=False, forecast_head=False
    )
    _load(agg.fuse, map_fusion(fx["public_state_dict"]))
    inp = fx["inputs"]
    with torch.no_grad():
        out = agg.fuse(torch.cat([from_zyx(inp["refined"]), from_zyx(inp["current"])], 1))
    return {"fused": max_relative_difference(out, from_zyx(fx["public_outputs"]["fused"]))}


def forecast_head(fx: dict[str, Any]) -> dict[str, float]:
    """The code's forecast head (bias-free last conv) = :class:`UpsampleDecoder` ``(C, C, K)``."""
    spec = STREAM_SPEC
    head = _load(
        UpsampleDecoder(spec["channels"], spec["channels"], spec["num_classes"], 2),
        map_forecast(fx["public_state_dict"]),
    )
    with torch.no_grad():
        logits = head(from_zyx(fx["inputs"]["refined"]))
    return {"logits": max_relative_difference(logits, fx["public_outputs"]["logits"])}  # the code's: (B, K, X, Y, Z)


def stream_agg(fx: dict[str, Any]) -> dict[str, float]:
    """The code's StreamAgg end to end (warp, reset, RefineNet, concat fusion) = :class:`StreamAggregation` with
    ``warp_sampling="public_linspace"`` and the code's reset (``|dt| > 2 s`` or ``dt = 0``; a negative gap warps)."""
    spec, inp = STREAM_SPEC, fx["inputs"]
    agg = StreamAggregation(
        spec["channels"],
        spec["num_classes"],
        _grid(spec),
        fusion="concat",
        residual_relu=True,
        occupied_hidden=spec["channels"] // 4,
        warp_sampling="public_linspace",
    )
    _load(agg, map_stream_agg(fx["public_state_dict"]))
    dt = inp["time_cur"] - inp["time_prev"]
    reset = (dt.abs() > 2.0) | (dt == 0)
    prev_to_current = torch.linalg.inv(inp["pose_cur"]) @ inp["pose_prev"]
    with torch.no_grad():
        out = agg(from_zyx(inp["current"]), from_zyx(inp["history"]), prev_to_current, reset).fused
    return {"fused": max_relative_difference(out, from_yxzc(fx["public_outputs"]["fused"]))}


def class_weights(fx: dict[str, Any]) -> dict[str, float]:
    """The code's ``5 / ln(f)`` class weights (free halved) = :func:`~.class_weights.duocc_class_weights`."""
    ours = duocc_class_weights(fx["inputs"]["counts"])
    return {"weights": max_relative_difference(ours, fx["public_outputs"]["weights"])}


def mask_matching(fx: dict[str, Any]) -> dict[str, float]:
    """The code's mask Hungarian assignment = :func:`~occplug_duocc.supervision.mask_decoder.match_masks`: the same
    cost matrix (over the camera-visible voxels) and the same query -> ground-truth assignment."""
    from occplug.nn import pairwise_dice_loss, pairwise_sigmoid_focal_loss

    from ..supervision.mask_decoder import match_masks

    inp, out = fx["inputs"], fx["public_outputs"]
    logits = inp["mask_logits"][:, inp["camera"]]  # (Q, V) at the counted voxels
    gts = inp["gt_masks"][:, inp["camera"]].float()
    cls = inp["cls_logits"]
    cost = (
        -cls.softmax(-1)[:, inp["gt_labels"]]
        + 20.0 * pairwise_sigmoid_focal_loss(logits, gts)
        + pairwise_dice_loss(logits, gts, 1.0)
    )
    query_idx, gt_idx = match_masks(cls, logits, inp["gt_labels"], gts)
    ours = torch.zeros_like(out["gt_inds"])  # the code's encoding: 0 unassigned, else 1 + the ground truth
    ours[query_idx] = gt_idx + 1
    return {
        "cost": max_relative_difference(cost, out["cost"]),
        "assignment": float((ours != out["gt_inds"]).float().mean()),
    }


#: module name -> its case.
CASES: dict[str, Callable[[dict[str, Any]], dict[str, float]]] = {
    "dqa": dqa,
    "v2q": v2q,
    "refinenet": refinenet,
    "occupied_head": occupied_head,
    "fusion": fusion,
    "forecast_head": forecast_head,
    "stream_agg": stream_agg,
    "decoder": decoder,
    "class_weights": class_weights,
    "mask_matching": mask_matching,
}

#: case -> the fixture file (``<name>.pt``) it reads: the occupied head is read off RefineNet's run.
FIXTURE_OF = {name: "refinenet" if name == "occupied_head" else name for name in CASES}
