"""Image encoders: ``small_cnn`` (plain PyTorch, CPU-cheap) and ``timm`` (any timm backbone)."""

from __future__ import annotations

import math
import os
from typing import Annotated, Any, Literal

import torch
from torch import Tensor, nn

from occplug.constraints import Positive, check_choices
from occplug.errors import UserError
from occplug.interfaces import ImageEncoder
from occplug.nn import BasicBlock2d, ConvNormAct2d

__all__ = ["SmallCNN", "TimmEncoder", "load_state_dict_file"]

# ImageNet statistics: images arrive in [0, 1] and are standardised inside the encoder.
_MEAN = (0.485, 0.456, 0.406)
_STD = (0.229, 0.224, 0.225)


def _check_divisible(images: Tensor, stride: int, who: str) -> None:
    h, w = images.shape[-2:]
    if h % stride or w % stride:
        raise UserError(
            f"{who}: image size {h}x{w} is not divisible by the encoder stride {stride}; "
            f"resize or crop the images (img_aug records it) to a multiple of {stride}"
        )


class _Standardise(nn.Module):
    """``(x - mean) / std`` with ImageNet statistics (buffers, not saved in checkpoints)."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("mean", torch.tensor(_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, x: Tensor) -> Tensor:
        return (x - self.mean.to(x.dtype)) / self.std.to(x.dtype)


class SmallCNN(ImageEncoder):
    """A small ResNet-style CNN in plain PyTorch, cheap enough for CPU training.

    Layout: a stride-2 3x3 stem (``width`` channels), then ``log2(stride) - 1`` stages, each a
    stride-2 :class:`~occplug.nn.BasicBlock2d` followed by ``num_blocks - 1``
    stride-1 blocks (stage ``i`` has ``width * 2**i`` channels), then a 1x1 conv to
    ``out_channels``. Feature cell ``(r, c)`` covers input pixels ``[s*r, s*r + s) x [s*c, s*c + s)``
    (``s`` = ``stride``); its centre is pixel ``u = s*c + (s-1)/2, v = s*r + (s-1)/2``.

    Args:
        out_channels: ``C`` of the output features.
        width: channels of the stem (doubled at each further stage).
        stride: input pixels per output cell, 4, 8 or 16. ``H`` and ``W`` must be divisible by it
            (a ``ValueError`` says so otherwise).
        num_blocks: residual blocks per stage (>= 1).
        norm: ``"batch"`` (BatchNorm) or ``"group"`` (GroupNorm, batch-size independent).
        levels: feature levels to output (>= 1). With more than one, each further level is a
            stride-2 :class:`~occplug.nn.BasicBlock2d` on the previous stage with
            its own 1x1 neck to ``out_channels``, so level ``i`` has stride ``stride * 2**i``;
            the first (finest) level is the primary one the view transform reads.
        finer_level: also output the features at ``stride / 2`` (the stage before the last, or the stem
            at ``stride`` 4) through their own 1x1 neck to ``out_channels``, as level 0, in front of the
            others; the primary level (``primary_level = 1``) and its weights' layout stay as without it.
            For consumers that want finer image features (an image-to-query detector on small objects)
            than the view transform reads.

    Shapes:
        input ``(B, N, 3, H, W)`` float RGB in [0, 1] (standardised inside with ImageNet
        statistics); output ``(B, N, out_channels, H // stride, W // stride)``, or with
        ``levels > 1`` a list of ``(B, N, out_channels, H // s_i, W // s_i)``, ``s_i = stride * 2**i``
        (``H`` and ``W`` must then be divisible by the coarsest ``s_i``). With ``finer_level`` the list
        starts with ``(B, N, out_channels, H // (stride / 2), W // (stride / 2))``.
    """

    def __init__(
        self,
        out_channels: Annotated[int, Positive] = 64,
        width: Annotated[int, Positive] = 32,
        stride: Literal[4, 8, 16] = 8,
        num_blocks: Annotated[int, Positive] = 1,
        norm: Literal["batch", "group"] = "batch",
        levels: Annotated[int, Positive] = 1,
        finer_level: bool = False,
    ) -> None:
        super().__init__()
        if levels < 1:
            raise ValueError(f"small_cnn levels must be >= 1, got {levels}")
        check_choices(SmallCNN.__init__, "small_cnn", stride=stride)
        if num_blocks < 1:
            raise ValueError(f"small_cnn num_blocks must be >= 1, got {num_blocks}")
        self.out_channels = int(out_channels)
        self.stride = int(stride)
        self.standardise = _Standardise()
        layers: list[nn.Module] = [ConvNormAct2d(3, width, 3, stride=2, norm=norm)]
        channels = width
        for i in range(int(math.log2(stride)) - 1):
            # the finer level reads the features before the last stage (at stride / 2)
            finer_channels, self._finer_after = channels, len(layers)
            out = width * 2**i
            layers.append(BasicBlock2d(channels, out, stride=2, norm=norm))
            layers.extend(BasicBlock2d(out, out, norm=norm) for _ in range(num_blocks - 1))
            channels = out
        self.body = nn.Sequential(*layers)
        self.neck = nn.Conv2d(channels, self.out_channels, 1)
        # coarser levels (multi-scale consumers such as image-to-query detectors); none by default
        self.down = nn.ModuleList(BasicBlock2d(channels, channels, stride=2, norm=norm) for _ in range(levels - 1))
        self.level_necks = nn.ModuleList(nn.Conv2d(channels, self.out_channels, 1) for _ in range(levels - 1))
        # the finest level (stride / 2), in front of the primary one; absent by default
        self.finer_neck = nn.Conv2d(finer_channels, self.out_channels, 1) if finer_level else None
        strides = tuple(self.stride * 2**i for i in range(levels))
        if finer_level:
            strides = (self.stride // 2, *strides)
            self.primary_level = 1
        if len(strides) > 1:
            self._level_channels = (self.out_channels,) * len(strides)
            self._level_strides = strides

    def forward(self, images: Tensor) -> Tensor | list[Tensor]:
        """``(B, N, 3, H, W)`` in [0, 1] -> ``(B, N, C, H / stride, W / stride)`` (or a list of levels)."""
        _check_divisible(images, self.level_strides[-1], "small_cnn")
        b, n = images.shape[:2]
        x = self.standardise(images.flatten(0, 1))
        out = []
        for i, layer in enumerate(self.body):
            if i == self._finer_after and self.finer_neck is not None:
                out.append(self.finer_neck(x))
            x = layer(x)
        out.append(self.neck(x))
        for down, neck in zip(self.down, self.level_necks, strict=True):
            x = down(x)
            out.append(neck(x))
        out = [level.view(b, n, *level.shape[1:]) for level in out]
        return out[0] if len(out) == 1 else out


def load_state_dict_file(path: str) -> dict[str, Tensor]:
    """Read a state dict from a local checkpoint file (never downloads).

    Accepts a bare state dict or one wrapped under ``"state_dict"`` or ``"model"``; loaded with
    ``torch.load(path, map_location="cpu", weights_only=True)``.

    Raises:
        FileNotFoundError: ``path`` does not exist.
    """
    if not os.path.isfile(path):
        raise FileNotFoundError(f"weights file not found: {path}")
    state: Any = torch.load(path, map_location="cpu", weights_only=True)
    for key in ("state_dict", "model"):
        if isinstance(state, dict) and isinstance(state.get(key), dict):
            state = state[key]
    if not isinstance(state, dict):
        raise ValueError(f"{path} does not hold a state dict (got {type(state).__name__})")
    return state


def _import_timm() -> Any:
    """``import timm``, or a :class:`UserError` naming the install that works beside this torch."""
    try:
        import timm
    except ImportError:
        raise ImportError("the 'timm' encoder needs timm: pip install 'occplug[timm]'") from None
    except Exception as exc:  # a torchvision built for another torch: RuntimeError
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise UserError(
            f"the 'timm' encoder: timm does not import ({type(exc).__name__}: {first}); timm needs a torchvision "
            f"built for this torch {torch.__version__} (PyPI's torchvision wheels need PyPI's torch: "
            "pip install torch==2.14.1 torchvision==0.29.1)"
        ) from None
    return timm


def _check_timm_state(state: dict[str, Any], model_name: str, weights: str) -> None:
    """Raise a one-line :class:`UserError` unless ``state`` holds every tensor of timm's ``model_name``.

    ``state`` is compared with the plain model (``timm.create_model(model_name)``, built on the meta
    device: names and shapes only, no memory): every tensor outside the classifier (``pretrained_cfg
    ["classifier"]``) must be in the file with its shape, and the file must hold nothing else. The
    classifier's keys may be missing or of another shape (a file saved with ``num_classes=0`` or a
    fine-tuned head).
    """
    timm = _import_timm()
    with torch.device("meta"):
        plain = timm.create_model(model_name, pretrained=False)
    classifier = plain.pretrained_cfg.get("classifier") or ()
    heads = tuple(f"{c}." for c in ((classifier,) if isinstance(classifier, str) else classifier))
    own = {k: v for k, v in plain.state_dict().items() if not k.startswith(heads)}
    given = {k: v for k, v in state.items() if not k.startswith(heads)}

    def listed(keys: list[str]) -> str:
        return ", ".join(keys[:3]) + (" ..." if len(keys) > 3 else "")

    missing = [k for k in own if k not in given]
    unexpected = [k for k in given if k not in own]
    if missing or unexpected:
        parts = [f"{len(missing)} missing key(s): {listed(missing)}"] if missing else []
        parts += [f"{len(unexpected)} unexpected key(s): {listed(unexpected)}"] if unexpected else []
        raise UserError(
            f"model.encoder.weights: {weights} is not a state dict of timm's '{model_name}' "
            f"({'; '.join(parts)}); expected a file saved as torch.save(timm.create_model('{model_name}').state_dict())"
        )
    for key, tensor in own.items():
        if tuple(given[key].shape) != tuple(tensor.shape):
            raise UserError(
                f"model.encoder.weights: {weights}: {key} is {tuple(given[key].shape)} but timm's "
                f"'{model_name}' has {tuple(tensor.shape)}"
            )


class TimmEncoder(ImageEncoder):
    """Any timm backbone (``features_only``) with a 1x1 conv neck to ``out_channels``.

    Needs the optional dependency timm (``pip install 'occplug[timm]'``; timm needs torchvision, and PyPI's
    torchvision needs PyPI's torch: ``torch==2.14.1 torchvision==0.29.1``). Nothing is ever downloaded: the
    backbone is built with ``pretrained=False`` or, if ``weights`` is given, through timm's own pretrained
    path from that local file: ``timm.models.load_state_dict`` reads it (``weights_only=True``; ``.pth`` or
    ``.safetensors``; a ``state_dict`` / ``model`` / EMA entry and ``module.`` prefixes unwrapped) and
    ``timm.create_model(..., pretrained=True, pretrained_cfg_overlay={"state_dict": ...})`` loads it into the
    plain model before timm wraps it in ``features_only`` (which renames ConvNeXt's ``stem.0`` to
    ``stem_0``). So the file is what a user saves, ``torch.save(timm.create_model(name).state_dict(), path)``
    (an ImageNet checkpoint of ``name``): every tensor outside the classifier must be there with its shape,
    else a one-line :class:`~occplug.errors.UserError` (exit code 2 from the CLI) names the first keys; the
    classifier's keys are not needed.

    Args:
        model_name: a timm model name, e.g. ``"resnet18"``, ``"convnext_tiny"``.
        out_channels: ``C`` of the output features (the neck's width).
        feature_level: which of the backbone's feature levels to use (timm ``out_indices``
            semantics; ``-1`` is the deepest). ``stride`` is that level's
            ``feature_info.reduction()``.
        weights: path to a local file holding timm's state dict of ``model_name``, or None.
        freeze: keep the backbone's parameters fixed and its norm layers in eval mode (the neck
            still trains).

    Shapes:
        input ``(B, N, 3, H, W)`` float RGB in [0, 1] (standardised inside with ImageNet
        statistics); output ``(B, N, out_channels, H // stride, W // stride)``; ``H`` and ``W``
        must be divisible by ``stride``.
    """

    def __init__(
        self,
        model_name: str,
        out_channels: Annotated[int, Positive] = 64,
        feature_level: int = -1,
        weights: str | None = None,
        freeze: bool = False,
    ) -> None:
        super().__init__()
        timm = _import_timm()
        if weights is not None and not os.path.isfile(weights):
            raise FileNotFoundError(f"timm encoder weights file not found: {weights}")
        self.model_name = model_name
        self.freeze = bool(freeze)
        self.standardise = _Standardise()
        features = {"features_only": True, "out_indices": (feature_level,)}
        if weights is None:
            self.backbone = timm.create_model(model_name, pretrained=False, **features)
        else:
            try:
                state = timm.models.load_state_dict(weights)
            except Exception as exc:  # torch.load and safetensors raise many types
                first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                raise UserError(f"model.encoder.weights: {weights} cannot be read as a state dict: {first}") from None
            _check_timm_state(state, model_name, weights)
            overlay = {"state_dict": state}
            self.backbone = timm.create_model(model_name, pretrained=True, pretrained_cfg_overlay=overlay, **features)
        self.stride = int(self.backbone.feature_info.reduction()[-1])
        self.out_channels = int(out_channels)
        self.neck = nn.Conv2d(int(self.backbone.feature_info.channels()[-1]), self.out_channels, 1)
        if self.freeze:
            self.backbone.requires_grad_(False)
            self.backbone.eval()

    def train(self, mode: bool = True) -> TimmEncoder:
        """Like :meth:`nn.Module.train`, but a frozen backbone stays in eval mode."""
        super().train(mode)
        if self.freeze:
            self.backbone.eval()
        return self

    def forward(self, images: Tensor) -> Tensor:
        """``(B, N, 3, H, W)`` in [0, 1] -> ``(B, N, C, H / stride, W / stride)``."""
        _check_divisible(images, self.stride, f"timm encoder '{self.model_name}'")
        b, n = images.shape[:2]
        x = self.neck(self.backbone(self.standardise(images.flatten(0, 1)))[-1])
        return x.view(b, n, *x.shape[1:])
