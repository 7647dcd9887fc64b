"""DuOcc's auxiliary RefineNet losses (paper §3.1 "Supervision for RefineNet", suppl. A.4) as supervision sources.

Both read the training-only logits ``duocc_stream`` publishes in ``outputs.extras`` and the current frame's voxel
labels; the paper weighs each by 10 (``L_bin``, ``L_fore``), the defaults here. In evaluation (no auxiliary
logits) they return no loss.
"""

from __future__ import annotations

from typing import Annotated, Any

import torch
from torch import Tensor

from occplug.constraints import NonNegative
from occplug.data.frame import Batch
from occplug.interfaces import ModelOutputs, SupervisionSource

from .scene import FORECAST_KEY, OCCUPIED_KEY
from .stream_agg import forecast_loss, occupied_loss

__all__ = ["DuOccForecast", "DuOccOccupied"]

_NO_LABEL = -1  # stands in for ignore_label None (no label id is negative)


class _AuxLoss(SupervisionSource):
    key: str
    switch: str

    def __init__(self, weight: float, camera_mask: bool, free_label: int, ignore_label: int | None) -> None:
        super().__init__()
        self.weight = float(weight)
        self.camera_mask = bool(camera_mask)
        self.free_label = int(free_label)
        self.ignore_label = _NO_LABEL if ignore_label is None else int(ignore_label)

    @property
    def training_mask(self) -> str:
        """``camera`` with ``camera_mask``, else ``none``."""
        return "camera" if self.camera_mask else "none"

    def logits(self, outputs: ModelOutputs) -> Tensor | None:
        """The auxiliary logits, or None outside training; a training forward without them is a config error."""
        logits = outputs.extras.get(self.key)
        if logits is None and self.training:
            raise ValueError(
                f"{type(self).__name__}: no '{self.key}' in the model's outputs; it needs model.scene.type=duocc_stream "
                f"with stream: true and {self.switch}: true"
            )
        return logits  # type: ignore[return-value]

    def mask(self, batch: Batch, labels: Tensor) -> Tensor:
        """``(B, X, Y, Z)`` bool: labelled samples, not ``voxel_invalid``, and ``mask_camera`` when asked."""
        keep = batch.has_voxel_labels.to(labels.device).view(-1, 1, 1, 1).expand_as(labels)
        if batch.voxel_invalid is not None:
            keep = keep & ~batch.voxel_invalid.bool()
        if self.camera_mask:
            batch.require("mask_camera", by=f"{type(self).__name__} with camera_mask")
            keep = keep & batch.mask_camera.bool()
        return keep

    @classmethod
    def _aux(cls, batch: Batch, grid: Any) -> Tensor:
        raise NotImplementedError

    @classmethod
    def conformance_outputs(cls, batch: Batch, grid: Any, channels: int) -> ModelOutputs:
        """Random auxiliary logits on the label grid (requiring grad) in ``extras``."""
        return ModelOutputs(None, None, None, {}, lambda *a, **k: None, extras={cls.key: cls._aux(batch, grid)})


class DuOccOccupied(_AuxLoss):
    """``L_bin``: BCE with logits of the occupied-mask head against "label is not free" (one sigmoid, in the loss).

    Args:
        weight: ``lambda_bin`` (paper: 10).
        camera_mask: count only ``batch.mask_camera`` voxels (as the occupancy loss).
        free_label, ignore_label: the data set's (filled in by the model).

    Reads ``outputs.extras["duocc_stream/occupied_logits"]`` ``(B, X, Y, Z)`` and ``batch.voxel_labels``
    ``(B, X, Y, Z)`` on the evaluation grid. Returns ``{"occupied_bce": scalar}`` (mean over counted voxels).
    """

    key = OCCUPIED_KEY
    switch = "occupied_head"

    def __init__(
        self,
        weight: Annotated[float, NonNegative] = 10.0,
        camera_mask: bool = True,
        free_label: int = 17,
        ignore_label: int | None = 255,
    ) -> None:
        super().__init__(weight, camera_mask, free_label, ignore_label)

    def forward(self, batch: Batch, outputs: ModelOutputs) -> dict[str, Tensor]:
        """``{"occupied_bce": loss}`` in training, ``{}`` when the head did not run."""
        logits = self.logits(outputs)
        if logits is None:
            return {}
        batch.require("voxel_labels", by="duocc_occupied")
        labels = batch.voxel_labels.long()
        mask = self.mask(batch, labels)
        return {"occupied_bce": occupied_loss(logits, labels, self.free_label, mask, self.ignore_label)}

    @classmethod
    def _aux(cls, batch: Batch, grid: Any) -> Tensor:
        return torch.randn(len(batch), *grid.shape, requires_grad=True)


class DuOccForecast(_AuxLoss):
    """``L_fore``: cross-entropy of the forecasting head (the refined history) against the current labels.

    Args:
        weight: ``lambda_fore`` (paper: 10).
        camera_mask: count only ``batch.mask_camera`` voxels.
        class_weights: ``K`` per-class weights, or None; the sum is divided by the counted voxels.
        free_label, ignore_label: the data set's (filled in by the model).

    Reads ``outputs.extras["duocc_stream/forecast_logits"]`` ``(B, K, X, Y, Z)`` and ``batch.voxel_labels``.
    Returns ``{"forecast_ce": scalar}``.
    """

    key = FORECAST_KEY
    switch = "forecast_head"

    def __init__(
        self,
        weight: Annotated[float, NonNegative] = 10.0,
        camera_mask: bool = True,
        class_weights: list[Annotated[float, NonNegative]] | None = None,
        free_label: int = 17,
        ignore_label: int | None = 255,
    ) -> None:
        super().__init__(weight, camera_mask, free_label, ignore_label)
        cw = None if class_weights is None else torch.tensor([float(v) for v in class_weights], dtype=torch.float32)
        self.register_buffer("class_weights", cw, persistent=False)

    def forward(self, batch: Batch, outputs: ModelOutputs) -> dict[str, Tensor]:
        """``{"forecast_ce": loss}`` in training, ``{}`` when the head did not run."""
        logits = self.logits(outputs)
        if logits is None:
            return {}
        batch.require("voxel_labels", by="duocc_forecast")
        labels = batch.voxel_labels.long()
        if self.class_weights is not None and self.class_weights.numel() != logits.shape[1]:
            raise ValueError(
                f"duocc_forecast: class_weights has {self.class_weights.numel()} entries, the logits "
                f"{logits.shape[1]} classes"
            )
        mask = self.mask(batch, labels)
        loss = forecast_loss(logits, labels, mask, self.class_weights, self.ignore_label)
        return {"forecast_ce": loss}

    @classmethod
    def _aux(cls, batch: Batch, grid: Any) -> Tensor:
        return torch.randn(len(batch), 18, *grid.shape, requires_grad=True)
