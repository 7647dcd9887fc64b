"""Write the public DuOcc code's module outputs as parity fixtures: ``python -m occplug_duocc.tools.public_parity MIRROR``.

``MIRROR`` is a local copy of ``github.com/moonseokha/DuOcc`` (a checkout, or a git directory: its ``HEAD`` is
extracted to a temporary folder). Run by hand, once, never in tests or CI: the fixtures it writes are figures, not
the code. For each module it builds the public one (its files imported from the mirror, with a pure-PyTorch stand-in
for the mmcv / mmdet / torch_geometric names they import, installed into ``sys.modules`` of this process only), gives
it seeded random weights (norm statistics included), feeds seeded random inputs and saves, per module, ``inputs``,
``public_state_dict`` and ``public_outputs`` (tensors only, ``weights_only=True``) to
``plugins/occplug_duocc/tests/fixtures/public_parity/<module>.pt``. It then runs occplug's module under the
``duocc/code_recipe`` switches on the mapped weights (:mod:`.public_weights`, :mod:`.public_parity_cases`) and
prints each module's max relative difference; the parity tests do the same from the fixtures alone.

Modules: ``dqa`` (with the cross-attention layer's FFN and closing LayerNorm), ``v2q``, ``refinenet`` (its
fixture also holds the ``occupied_head``'s output), ``fusion``, ``forecast_head``, ``stream_agg`` (end to end, warp included), ``decoder``,
``class_weights``, ``mask_matching``.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import inspect
import math
import subprocess
import sys
import tempfile
import types
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .public_parity_cases import CASES, FIXTURE_DIR, FIXTURE_OF
from .public_weights import DQA_SPEC, STREAM_SPEC, V2Q_SPEC

__all__ = ["main"]

PLUGIN = "projects.mmdet3d_plugin"


# ---------------------------------------------------------------------------------------------- stand-ins


class _Registry:
    """mmcv's ``Registry``: a name -> class table filled by ``register_module()``."""

    def __init__(self, name: str) -> None:
        self.name, self.table = name, {}

    def register_module(self, name: str | None = None, force: bool = False, module: Any = None) -> Any:
        def add(cls: Any) -> Any:
            self.table[name or cls.__name__] = cls
            return cls

        return add(module) if module is not None else add

    def get(self, name: str) -> Any:
        return self.table[name]


def _build_from_cfg(cfg: dict, registry: _Registry, default_args: dict | None = None) -> Any:
    args = dict(cfg)
    kind = args.pop("type")
    return registry.get(kind)(**args, **(default_args or {}))


class _BaseModule(nn.Module):
    def __init__(self, init_cfg: Any = None) -> None:
        super().__init__()
        self.init_cfg = init_cfg


def _layer(kinds: dict[str, type]) -> Any:
    def build(cfg: dict, *args: Any, **kwargs: Any) -> nn.Module:
        extra = dict(cfg)
        return kinds[extra.pop("type")](*args, **kwargs, **extra)

    return build


def _build_norm_layer(cfg: dict, num_features: int) -> tuple[str, nn.Module]:
    extra = dict(cfg)
    kind = extra.pop("type")
    extra.pop("requires_grad", None)
    if kind == "GN":
        return "gn", nn.GroupNorm(extra.pop("num_groups"), num_features, **extra)
    if kind == "LN":
        return "ln", nn.LayerNorm(num_features, **extra)
    return "bn", {"BN": nn.BatchNorm2d, "BN3d": nn.BatchNorm3d, "BN1d": nn.BatchNorm1d}[kind](num_features, **extra)


class _ConvModule(nn.Module):
    """mmcv's ``ConvModule`` as the public code uses it: a conv (``conv``), no norm, then ReLU."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, stride: int = 1, padding: int = 0,
                 bias: bool | str = True, conv_cfg: dict | None = None, norm_cfg: dict | None = None,
                 act_cfg: dict | None = None, **_: Any) -> None:  # fmt: skip
        super().__init__()
        if norm_cfg is not None:
            raise NotImplementedError("public_parity: ConvModule with a norm is not stood in for")
        kind = {"Conv3d": nn.Conv3d, "Conv2d": nn.Conv2d}[(conv_cfg or {"type": "Conv2d"})["type"]]
        self.conv = kind(in_channels, out_channels, kernel_size, stride, padding, bias=bool(bias))
        self.activate = nn.ReLU(inplace=True)

    def forward(self, x: Tensor) -> Tensor:
        return self.activate(self.conv(x))


def _xavier_init(module: nn.Module, gain: float = 1.0, bias: float = 0.0, distribution: str = "normal") -> None:
    (nn.init.xavier_uniform_ if distribution == "uniform" else nn.init.xavier_normal_)(module.weight, gain=gain)
    if getattr(module, "bias", None) is not None:
        nn.init.constant_(module.bias, bias)


def _constant_init(module: nn.Module, val: float, bias: float = 0.0) -> None:
    nn.init.constant_(module.weight, val)
    if getattr(module, "bias", None) is not None:
        nn.init.constant_(module.bias, bias)


def _deformable_attn_3d(value: Tensor, spatial_shapes: Tensor, locations: Tensor, weights: Tensor) -> Tensor:
    """The public 3D deformable attention kernel (``deform_attn_3d``) in PyTorch, for one level.

    ``value (B, N, heads, d)`` over an ``(H, W, Z)`` volume (flat ``(h * W + w) * Z + z``), ``locations
    (B, Q, heads, 1, P, 3)`` in ``[0, 1]`` as ``(w, h, z)`` read at ``loc * size - 0.5`` with zeros outside (the
    kernel's), ``weights (B, Q, heads, 1, P)`` -> ``(B, Q, heads * d)``.
    """
    b, _, heads, d = value.shape
    h, w, z = (int(s) for s in spatial_shapes[0])
    q, p = locations.shape[1], locations.shape[4]
    vol = value.view(b, h, w, z, heads, d).permute(0, 4, 5, 1, 2, 3).reshape(b * heads, d, h, w, z)
    loc = locations[:, :, :, 0].permute(0, 2, 1, 3, 4).reshape(b * heads, q, p, 3)  # (w, h, z) in [0, 1]
    grid = torch.stack([loc[..., 2], loc[..., 0], loc[..., 1]], -1) * 2 - 1  # grid_sample's (W, H, D) = (z, w, h)
    sampled = F.grid_sample(vol, grid[:, None], mode="bilinear", padding_mode="zeros", align_corners=False)
    sampled = sampled[:, :, 0]  # (B * heads, d, Q, P)
    wts = weights[:, :, :, 0].permute(0, 2, 1, 3).reshape(b * heads, 1, q, p)
    out = (sampled * wts).sum(-1).view(b, heads * d, q)
    return out.transpose(1, 2).contiguous()


class _MessagePassing(nn.Module):
    """torch_geometric's ``MessagePassing`` (``aggr="add"``, source-to-target flow) for the public DQA."""

    def __init__(self, aggr: str = "add", node_dim: int = 0, **_: Any) -> None:
        super().__init__()
        if aggr != "add":
            raise NotImplementedError(aggr)

    def propagate(self, edge_index: Tensor, size: Any = None, **kwargs: Any) -> Tensor:
        j, i = edge_index
        x = kwargs["x"]
        x_src, x_dst = x if isinstance(x, tuple) else (x, x)
        args: dict[str, Any] = {}
        for name in inspect.signature(self.message).parameters:
            if name in ("index",):
                args[name] = i
            elif name == "ptr":
                args[name] = None
            elif name == "size_i":
                args[name] = x_dst.shape[0]
            elif name.endswith(("_i", "_j")):
                base, side = name[:-2], name[-1]
                val = kwargs.get(base)
                if base == "x":
                    val = x_dst if side == "i" else x_src
                elif isinstance(val, tuple):
                    val = val[1] if side == "i" else val[0]
                args[name] = None if val is None else val[i if side == "i" else j]
            else:
                args[name] = kwargs.get(name)
        msg = self.message(**args)
        out = msg.new_zeros(x_dst.shape[0], *msg.shape[1:]).index_add_(0, i, msg)
        return self.update(out, x=x)

    def update(self, inputs: Tensor, **_: Any) -> Tensor:
        return inputs


def _pyg_softmax(src: Tensor, index: Tensor, ptr: Any = None, num_nodes: int | None = None, dim: int = 0) -> Tensor:
    """torch_geometric's scatter softmax over ``index`` groups (its ``1e-16`` in the denominator)."""
    n = int(num_nodes if num_nodes is not None else index.max() + 1)
    at = index.view(-1, *([1] * (src.dim() - 1))).expand_as(src)
    top = src.new_full((n, *src.shape[1:]), -math.inf).scatter_reduce(0, at, src, "amax", include_self=True)
    e = (src - top[index]).exp()
    total = src.new_zeros((n, *src.shape[1:])).index_add_(0, index, e)
    return e / (total[index] + 1e-16)


class _AssignResult:
    """mmdet's ``AssignResult``: what an assigner returns."""

    def __init__(self, num_gts: int, gt_inds: Tensor, max_overlaps: Any, labels: Any = None) -> None:
        self.num_gts, self.gt_inds, self.max_overlaps, self.labels = num_gts, gt_inds, max_overlaps, labels


def _install(root: Path) -> None:
    """Stand-ins for the names the public files import, and the plugin's packages without their ``__init__``."""

    def module(name: str, **attrs: Any) -> types.ModuleType:
        mod = sys.modules.get(name) or types.ModuleType(name)
        mod.__dict__.update(attrs)
        sys.modules[name] = mod
        if "." in name:
            parent, _, child = name.rpartition(".")
            setattr(module(parent), child, mod)
        return mod

    reg = {n: _Registry(n) for n in ("PLUGIN_LAYERS", "ATTENTION", "FEEDFORWARD_NETWORK", "POSITIONAL_ENCODING")}
    mmdet_reg = {n: _Registry(n) for n in ("BACKBONES", "NECKS", "HEADS", "LOSSES")}
    conv = _layer({"Conv3d": nn.Conv3d, "Conv2d": nn.Conv2d})
    upsample = _layer({"deconv3d": nn.ConvTranspose3d, "deconv": nn.ConvTranspose2d})
    module("mmcv")
    module("mmcv.cnn", Linear=nn.Linear, build_activation_layer=lambda cfg: nn.ReLU(inplace=True),
           build_norm_layer=_build_norm_layer, xavier_init=_xavier_init, constant_init=_constant_init,
           Scale=None, bias_init_with_prob=lambda p: float(-math.log((1 - p) / p)), build_conv_layer=conv,
           build_upsample_layer=upsample)  # fmt: skip
    module("mmcv.cnn.bricks")
    module("mmcv.cnn.bricks.registry", **reg)
    module("mmcv.cnn.bricks.conv_module", ConvModule=_ConvModule)
    module("mmcv.cnn.bricks.transformer", FFN=None, POSITIONAL_ENCODING=reg["POSITIONAL_ENCODING"],
           build_positional_encoding=lambda cfg: _build_from_cfg(cfg, reg["POSITIONAL_ENCODING"]))  # fmt: skip
    module("mmcv.cnn.bricks.drop", build_dropout=lambda cfg: nn.Dropout(cfg.get("drop_prob", 0.0)))
    module("mmcv.runner", BaseModule=_BaseModule, force_fp32=lambda *a, **k: lambda f: f)
    module("mmcv.runner.base_module", BaseModule=_BaseModule, Sequential=nn.Sequential)
    module("mmcv.utils", build_from_cfg=_build_from_cfg, ext_loader=None)
    module("mmcv.ops")
    module("mmcv.ops.multi_scale_deform_attn", multi_scale_deformable_attn_pytorch=_deformable_attn_3d)
    build = {f"build_{k}": (lambda r: lambda cfg: _build_from_cfg(cfg, r))(mmdet_reg[n])
             for k, n in (("backbone", "BACKBONES"), ("neck", "NECKS"), ("head", "HEADS"))}  # fmt: skip
    module("mmdet")
    module("mmdet.core", multi_apply=lambda f, *a, **k: tuple(map(list, zip(*map(f, *a), strict=True))))
    match_cost = _Registry("MATCH_COST")
    module("mmdet.core.bbox")
    module("mmdet.core.bbox.builder", BBOX_ASSIGNERS=_Registry("BBOX_ASSIGNERS"))
    module("mmdet.core.bbox.match_costs")
    module("mmdet.core.bbox.match_costs.builder", MATCH_COST=match_cost,
           build_match_cost=lambda cfg: _build_from_cfg(cfg, match_cost))  # fmt: skip
    module("mmdet.core.bbox.assigners", AssignResult=_AssignResult, BaseAssigner=object)
    module("mmdet.models", **mmdet_reg, **build)
    module("mmdet.models.builder", **mmdet_reg, **build)
    module("torch_geometric")
    module("torch_geometric.nn")
    module("torch_geometric.nn.conv", MessagePassing=_MessagePassing)
    module("torch_geometric.typing", Adj=Tensor, OptTensor=Any, Size=Any)
    module("torch_geometric.utils", softmax=_pyg_softmax)
    # the plugin's packages, their __init__ not run (it imports the whole model); a submodule loads on its own
    base = root / "projects" / "mmdet3d_plugin"
    for d in [base.parent, base, *(p for p in base.rglob("*") if p.is_dir())]:
        name = ".".join(d.relative_to(root).parts)
        mod = module(name)
        mod.__path__ = [str(d)]
    # the compiled CUDA op of the 3D deformable attention: the CPU path never calls it
    module(f"{PLUGIN}.models.heads.mask_head.multi_scale_deformable_attn_3D_custom_function",
           MultiScaleDeformableAttn3DCustomFunction_fp16=None,
           MultiScaleDeformableAttn3DCustomFunction_fp32=None)  # fmt: skip


def _public(name: str) -> types.ModuleType:
    return importlib.import_module(f"{PLUGIN}.{name}")


def _checkout(mirror: Path, scratch: Path) -> Path:
    """A folder holding the mirror's files: the mirror itself, or its git ``HEAD`` extracted into ``scratch``."""
    if (mirror / "projects" / "mmdet3d_plugin").is_dir():
        return mirror
    archive = subprocess.run(["git", "--git-dir", str(mirror), "archive", "HEAD"], capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(scratch)], input=archive.stdout, check=True)
    return scratch


# ---------------------------------------------------------------------------------------------- cases


def _randomise(module: nn.Module, gen: torch.Generator) -> None:
    """Seeded random weights everywhere, norm statistics included (a zero-initialised layer would hide a mapping)."""

    def rnd(*shape: int) -> Tensor:
        return torch.randn(*shape, generator=gen)

    with torch.no_grad():
        for m in module.modules():
            if isinstance(m, (nn.LayerNorm, nn.GroupNorm, nn.modules.batchnorm._BatchNorm)):
                m.weight.copy_(1 + 0.3 * rnd(*m.weight.shape))
                m.bias.copy_(0.2 * rnd(*m.bias.shape))
                if isinstance(m, nn.modules.batchnorm._BatchNorm):
                    m.running_mean.copy_(0.2 * rnd(*m.running_mean.shape))
                    m.running_var.copy_(0.5 + torch.rand(*m.running_var.shape, generator=gen))
            elif isinstance(m, (nn.Linear, nn.Conv3d, nn.ConvTranspose3d)):
                fan_in = m.weight[0].numel() if not isinstance(m, nn.ConvTranspose3d) else m.weight.shape[0] * 8
                m.weight.copy_(rnd(*m.weight.shape) / math.sqrt(fan_in))
                if m.bias is not None:
                    m.bias.copy_(0.2 * rnd(*m.bias.shape))
            elif isinstance(m, nn.Embedding):
                m.weight.copy_(0.5 * rnd(*m.weight.shape))


def _state(module: nn.Module, prefix: str = "") -> dict[str, Tensor]:
    return {f"{prefix}{k}": v.detach().clone() for k, v in module.state_dict().items()}


def _grid_config(spec: dict) -> dict[str, list[float]]:
    lo, hi, v = spec["range"][:3], spec["range"][3:], spec["voxel"]
    return {axis: [lo[i], hi[i], v] for i, axis in enumerate("xyz")} | {"range": list(spec["range"])}


def _boxes(gen: torch.Generator, b: int, q: int, spread: float) -> Tensor:
    """``(B, Q, 11)`` encoded boxes with a raw, unnormalised ``(sin, cos)`` (norm 0.7 to 1.3)."""
    centre = (torch.rand(b, q, 3, generator=gen) * 2 - 1) * torch.tensor([spread, spread, 1.5])
    size = (torch.rand(b, q, 3, generator=gen) * 2.5 + 0.8).log()
    yaw = torch.rand(b, q, 1, generator=gen) * 2 * math.pi
    norm = 0.7 + 0.6 * torch.rand(b, q, 1, generator=gen)
    vel = torch.randn(b, q, 3, generator=gen)
    return torch.cat([centre, size, norm * yaw.sin(), norm * yaw.cos(), vel], -1)


def case_dqa(gen: torch.Generator) -> dict[str, Any]:
    spec = DQA_SPEC
    c, heads = spec["channels"], spec["heads"]
    dqa = _public("models.heads.queryagg.dqa").DQA(
        c, grid_config=_grid_config(spec), num_heads=heads, without_occ=True, dropout=0.0
    )
    pe_cls = _public("models.heads.common.positional_encoding").CustomLearnedPositionalEncoding3D
    nx = int(round((spec["range"][3] - spec["range"][0]) / spec["voxel"]))
    nz = int(round((spec["range"][5] - spec["range"][2]) / spec["voxel"]))
    cxy = 3 * c // 8
    pe = pe_cls([cxy, cxy, c - 2 * cxy], row_num_embed=nx, col_num_embed=nx, tub_num_embed=nz)
    _randomise(dqa, gen), _randomise(pe, gen)
    dqa.eval(), pe.eval()
    b, q = 3, 6
    feats = torch.randn(b, q, c, generator=gen)
    vox = torch.randn(b, nx, nx, nz, c, generator=gen)  # (B, Y, X, Z, C)
    boxes = _boxes(gen, b, q, 3.5)
    boxes[0, 0, :3] = torch.tensor([6.3, 0.4, 0.2])  # wholly off the grid (+x): clamped onto the face slab
    boxes[1, 2, :3] = torch.tensor([-0.5, -7.0, 3.1])  # off in -y and +z
    selected = torch.rand(b, q, generator=gen) > 0.35
    selected[0, 0] = selected[1, 2] = True
    selected[2] = False  # nothing selected: the code's zero-feature dummy query (query 0)
    with torch.no_grad():
        pos = pe(torch.zeros(b, nx, nx, nz)).permute(0, 2, 3, 4, 1).reshape(b, -1, c)  # (B, N, C), (y, x, z)
        indices, query_feature = [], feats.clone()
        for i in range(b):  # as the code's QueryAgg: an empty selection is query 0 with zeroed features
            idx = selected[i].nonzero().flatten()
            if idx.numel() == 0:
                idx = torch.tensor([0])
                query_feature[i] = 0
            indices.append(idx)
        out, _, _ = dqa(query_feature, vox.clone(), boxes, indices, metas=None, voxel_pos=pos)
    return {
        "inputs": {"queries": feats, "volume": vox, "boxes": boxes, "selected": selected},
        "public_state_dict": {**_state(dqa), **_state(pe, "pos.")},
        "public_outputs": {"volume": out},
    }


def case_decoder(gen: torch.Generator) -> dict[str, Any]:
    spec = DQA_SPEC
    c, k = spec["channels"], spec["num_classes"]
    dqa = _public("models.heads.queryagg.dqa").DQA(
        c, grid_config=_grid_config(spec), num_classes=k, query_to_vox=False, dropout=0.0
    )
    _randomise(dqa, gen)
    dqa.eval()
    nx = int(round((spec["range"][3] - spec["range"][0]) / spec["voxel"]))
    nz = int(round((spec["range"][5] - spec["range"][2]) / spec["voxel"]))
    vox = torch.randn(2, nx, nx, nz, c, generator=gen)
    with torch.no_grad():
        _, logits, _ = dqa(vox_feat=vox.clone())
    sd = {key: v for key, v in _state(dqa).items() if key.split(".")[0] in ("up_block", "proj_layer", "vox_occ_net")}
    return {"inputs": {"volume": vox}, "public_state_dict": sd, "public_outputs": {"logits": logits}}


def case_v2q(gen: torch.Generator) -> dict[str, Any]:
    spec = V2Q_SPEC
    c, heads, points = spec["channels"], spec["heads"], spec["points"]
    fixed = [[0, 0, 0], [0.45, 0, 0], [-0.45, 0, 0], [0, 0.45, 0], [0, -0.45, 0], [0, 0, 0.45], [0, 0, -0.45]]
    _public("models.heads.queryagg.detection3d_blocks")  # registers the key point generator
    _public("models.heads.mask_head.deformable_cross_attention_3D")  # registers DeformCrossAttention3D
    dfa = _public("models.heads.queryagg.blocks").DeformableFeatureAggregation(
        embed_dims=c,
        num_groups=heads,
        num_levels=1,
        num_cams=6,
        attn_drop=0.15,
        use_voxel_feature=True,
        use_deformable_func=False,
        use_camera_embed=True,
        residual_mode="add",
        attn_cfgs={
            "type": "DeformCrossAttention3D",
            "embed_dims": c,
            "grid_config": _grid_config(spec),
            "num_heads": heads,
            "num_levels": 1,
            "num_points": points,
            "dropout": 0.0,
        },
        kps_generator={"type": "SparseBox3DKeyPointsGenerator", "num_learnable_pts": points, "fix_scale": fixed},
    )
    _randomise(dfa, gen)
    dfa.eval()
    nx = int(round((spec["range"][3] - spec["range"][0]) / spec["voxel"]))
    nz = int(round((spec["range"][5] - spec["range"][2]) / spec["voxel"]))
    b, q = 2, 5
    feats = torch.randn(b, q, c, generator=gen)
    embed = torch.randn(b, q, c, generator=gen)
    boxes = _boxes(gen, b, q, 4.5)  # some near or past the faces: zero padding
    vox = torch.randn(b, nx, nx, nz, c, generator=gen)
    with torch.no_grad():
        out = dfa(feats, boxes, embed, None, vox.clone(), {})
    return {
        "inputs": {"queries": feats, "anchor_embed": embed, "boxes": boxes, "volume": vox},
        "public_state_dict": _state(dfa),
        "public_outputs": {"queries": out},
    }


def _stream_agg(spec: dict) -> nn.Module:
    c = spec["channels"]
    _public("models.heads.streamagg.refinenet")  # registers RefineNet
    return _public("models.heads.streamagg.streamagg").StreamAgg(
        c,
        refine_net_cfg={"type": "RefineNet", "channels": c, "internal_channels": c // 4, "use_occupied_head": True},
        use_forecast_head=True,
        grid_config=_grid_config(spec),
        temp_cat_method="cat",
        num_classes=spec["num_classes"],
    )


def _zyx(spec: dict, b: int, gen: torch.Generator) -> Tensor:
    n = [int(round((spec["range"][i + 3] - spec["range"][i]) / spec["voxel"])) for i in range(3)]
    return torch.randn(b, spec["channels"], n[2], n[1], n[0], generator=gen)  # (B, C, Z, Y, X)


def case_refinenet(gen: torch.Generator) -> dict[str, Any]:
    spec = STREAM_SPEC
    c = spec["channels"]
    net = _public("models.heads.streamagg.refinenet").RefineNet(c, c // 4, use_occupied_head=True)
    _randomise(net, gen)
    net.eval()
    x = _zyx(spec, 2, gen)
    with torch.no_grad():
        out, occupied = net(x.clone())
    return {
        "inputs": {"volume": x},
        "public_state_dict": _state(net),
        "public_outputs": {"refined": out, "occupied": occupied},
    }


def case_fusion(gen: torch.Generator) -> dict[str, Any]:
    agg = _stream_agg(STREAM_SPEC)
    _randomise(agg, gen)
    agg.eval()
    refined, current = _zyx(STREAM_SPEC, 2, gen), _zyx(STREAM_SPEC, 2, gen)
    with torch.no_grad():
        out = agg.cat_block(torch.cat([refined, current], 1))
    sd = {k: v for k, v in _state(agg).items() if k.startswith("cat_block.")}
    return {
        "inputs": {"refined": refined, "current": current},
        "public_state_dict": sd,
        "public_outputs": {"fused": out},
    }


def case_forecast_head(gen: torch.Generator) -> dict[str, Any]:
    agg = _stream_agg(STREAM_SPEC)
    _randomise(agg, gen)
    agg.train()  # the forecast head runs in training only
    for m in agg.modules():  # ... with the norm statistics frozen, as the fixture's inference-mode comparison
        if isinstance(m, nn.modules.batchnorm._BatchNorm):
            m.eval()
    current, history = _zyx(STREAM_SPEC, 2, gen), _zyx(STREAM_SPEC, 2, gen)
    with torch.no_grad():
        refined, _ = agg.temporal_conv_net(history.clone())
        _, forecasts, _ = agg(current.clone(), history.clone())
    sd = {k: v for k, v in _state(agg).items() if k.startswith(("pred_up_block.", "forecast_occ_net."))}
    # its output is permuted to (B, K, X, Y, Z) by the code
    return {"inputs": {"refined": refined}, "public_state_dict": sd, "public_outputs": {"logits": forecasts[0]}}


def case_stream_agg(gen: torch.Generator) -> dict[str, Any]:
    from occplug.geometry import make_pose, rotation_z

    agg = _stream_agg(STREAM_SPEC)
    _randomise(agg, gen)
    agg.eval()
    current, history = _zyx(STREAM_SPEC, 3, gen), _zyx(STREAM_SPEC, 3, gen)
    yaw = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    t_prev = torch.tensor([[1.2, -0.7, 0.1], [0.0, 0.5, 0.0], [-0.6, 0.3, 0.0]], dtype=torch.float64)
    pose_prev = torch.stack([make_pose(rotation_z(y), t) for y, t in zip(yaw, t_prev, strict=True)])
    step = make_pose(rotation_z(torch.tensor(0.15, dtype=torch.float64)), torch.tensor([0.9, 0.4, 0.0]).double())
    pose_cur = pose_prev @ step  # current ego -> global
    time_prev = torch.tensor([10.0, 10.0, 10.0], dtype=torch.float64)
    time_cur = torch.tensor([10.5, 13.0, 9.0], dtype=torch.float64)  # dt 0.5 (warp), 3.0 (reset), -1.0 (the code warps)
    metas = {"timestamp": time_cur, "img_metas": [{"T_global": p.numpy()} for p in pose_cur]}
    bank = types.SimpleNamespace(
        cached_anchor=None,
        cached_vox_feature=history.clone(),
        metas={"timestamp": time_prev, "img_metas": [{"T_global_inv": p.inverse().numpy()} for p in pose_prev]},
    )
    with torch.no_grad():
        out, _, _ = agg.forward_voxel_stage(current.clone(), metas, bank, training=False)
    return {
        "inputs": {
            "current": current,
            "history": history,
            "pose_prev": pose_prev,
            "pose_cur": pose_cur,
            "time_prev": time_prev,
            "time_cur": time_cur,
        },
        "public_state_dict": _state(agg),
        "public_outputs": {"fused": out},  # (B, Y, X, Z, C)
    }


def case_class_weights(gen: torch.Generator, root: Path) -> dict[str, Any]:
    tree = ast.parse((root / "projects" / "configs" / "DuOcc.py").read_text())
    counts = next(
        ast.literal_eval(node.value)
        for node in tree.body
        if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == "nusc_class_frequencies"
    )
    head = _public("models.heads.duocc_head").DuOccHead(loss_occ=types.SimpleNamespace(), cls_freq=counts)
    return {
        "inputs": {"counts": torch.tensor(counts, dtype=torch.float64)},
        "public_state_dict": {},
        "public_outputs": {"weights": torch.as_tensor(head.loss_occ.class_weight)},
    }


def case_mask_matching(gen: torch.Generator) -> dict[str, Any]:
    """The code's mask decoder assignment (``MaskHungarianAssigner3D`` with its config's costs 1 / 20 / 1)."""
    _public("models.assigners.match_costs.match_cost")  # registers the costs
    assigner = _public("models.assigners.mask_hungarian_assigner").MaskHungarianAssigner3D(
        cls_cost={"type": "MaskClassificationCost", "weight": 1.0},
        mask_cost={"type": "MaskFocalLossCost", "weight": 20.0, "binary_input": True},
        dice_cost={"type": "MaskDiceLossCost", "weight": 1.0, "pred_act": True, "eps": 1.0},
        use_camera_mask=True,
        use_lidar_mask=False,
    )
    q, k, m, shape = 12, 6, 5, (8, 8, 4)
    cls_logits = 2 * torch.randn(q, k + 1, generator=gen)
    mask_logits = 3 * torch.randn(q, *shape, generator=gen)
    gt_labels = torch.randperm(k + 1, generator=gen)[:m]
    owner = torch.randint(0, m, shape, generator=gen)  # one ground-truth mask per voxel (as a semantic grid)
    gt_masks = torch.stack([owner == i for i in range(m)])
    camera = torch.rand(shape, generator=gen) > 0.3
    result = assigner.assign(cls_logits, mask_logits, gt_labels, gt_masks, mask_camera=camera)
    flat_pred, flat_gt = mask_logits[:, camera].flatten(1), gt_masks[:, camera].flatten(1).float()
    cost = (
        assigner.cls_cost(cls_logits, gt_labels)
        + assigner.mask_cost(flat_pred, flat_gt)
        + assigner.dice_cost(flat_pred, flat_gt)
    )
    return {
        "inputs": {
            "cls_logits": cls_logits,
            "mask_logits": mask_logits,
            "gt_labels": gt_labels,
            "gt_masks": gt_masks,
            "camera": camera,
        },
        "public_state_dict": {},
        "public_outputs": {"gt_inds": result.gt_inds, "cost": cost},
    }


BUILDERS = {
    "dqa": case_dqa,
    "v2q": case_v2q,
    "refinenet": case_refinenet,
    "fusion": case_fusion,
    "forecast_head": case_forecast_head,
    "stream_agg": case_stream_agg,
    "decoder": case_decoder,
    "class_weights": case_class_weights,
    "mask_matching": case_mask_matching,
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m occplug_duocc.tools.public_parity", description=__doc__)
    parser.add_argument("mirror", type=Path, help="a checkout or git directory of github.com/moonseokha/DuOcc")
    parser.add_argument("--out", type=Path, default=FIXTURE_DIR, help="fixture folder (default: the plugin's)")
    parser.add_argument("--modules", nargs="*", default=list(BUILDERS), choices=list(BUILDERS))
    args = parser.parse_args(argv)
    if not args.mirror.exists():
        print(f"public_parity: mirror {args.mirror} does not exist", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as scratch:
        root = _checkout(args.mirror, Path(scratch))
        sys.path.insert(0, str(root))
        _install(root)
        args.out.mkdir(parents=True, exist_ok=True)
        for seed, name in enumerate(BUILDERS):
            if name not in args.modules:
                continue
            gen = torch.Generator().manual_seed(1000 + seed)
            build = BUILDERS[name]
            fixture = build(gen, root) if name == "class_weights" else build(gen)
            path = args.out / f"{name}.pt"
            torch.save(fixture, path)
            loaded = torch.load(path, weights_only=True)
            for case in [c for c, f in FIXTURE_OF.items() if f == name]:
                diffs = CASES[case](loaded)
                worst = ", ".join(f"{k} {v:.2e}" for k, v in diffs.items())
                print(
                    f"{case:14s} {path.name:18s} {path.stat().st_size / 1024:6.1f} KB  max relative difference: {worst}"
                )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
