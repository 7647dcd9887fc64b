"""DuOcc's auxiliary losses (suppl. A.4) as supervision sources.

``duocc_occupied`` / ``duocc_forecast`` (§3.1 "Supervision for RefineNet") read the training-only logits
``duocc_stream`` publishes in ``outputs.extras`` and the current frame's voxel labels; the paper weighs each by 10
(``L_bin``, ``L_fore``), the defaults here. In evaluation (no auxiliary logits) they return no loss.
``duocc_detection`` (``L_det``, weight 0.2) trains QueryAgg's image-to-query detector on ``batch.boxes``.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import torch
from torch import Tensor

from occplug.constraints import NonNegative, UnitInterval, check_choices
from occplug.data import Batch
from occplug.interfaces import ModelOutputs, SupervisionSource

from ..blocks.detection_loss import detection_loss
from ..blocks.detector import DetectorOutput
from ..blocks.queryagg import detection_targets
from ..blocks.stream_agg import forecast_loss, occupied_loss
from ..scene import DETECTION_CLASSES_KEY, DETECTION_KEY, FORECAST_KEY, OCCUPIED_KEY

__all__ = ["DuOccDetection", "DuOccForecast", "DuOccOccupied"]

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
        weighting: ``per_voxel`` (the mean BCE, every counted voxel alike: the paper's BCE) or ``public_mean``
            (the public code's: that mean times the mean of its 1.0 occupied / 0.1 free voxel weights, a
            factor ``0.1 + 0.9 x`` occupied fraction of the batch; :func:`~occplug_duocc.blocks.stream_agg.occupied_loss`).
        head_sigmoid: apply a sigmoid to the head's output before the BCE with logits, as the public code's head
            does (so two sigmoids; its BCE then sees values in ``(0, 1)`` as logits). Default off.

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
        weighting: Literal["per_voxel", "public_mean"] = "per_voxel",
        head_sigmoid: bool = False,
    ) -> None:
        super().__init__(weight, camera_mask, free_label, ignore_label)
        check_choices(DuOccOccupied.__init__, "duocc_occupied", weighting=weighting)
        self.weighting = weighting
        self.head_sigmoid = bool(head_sigmoid)

    def forward(self, batch: Batch, outputs: ModelOutputs) -> dict[str, Tensor]:
        """``{"occupied_bce": loss}`` in training, ``{}`` when the head did not run."""
        logits = self.logits(outputs)
        if logits is None:
            return {}
        batch.require("voxel_labels", by="duocc_occupied")
        labels = batch.voxel_labels.long()
        mask = self.mask(batch, labels)
        if self.head_sigmoid:
            logits = torch.sigmoid(logits)
        loss = occupied_loss(logits, labels, self.free_label, mask, self.ignore_label, weighting=self.weighting)
        return {"occupied_bce": loss}

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


class DuOccDetection(SupervisionSource):
    """``L_det``: Sparse4D v3's detection loss (:func:`~occplug_duocc.blocks.detection_loss.detection_loss`) on QueryAgg's detector.

    Reads ``outputs.extras["duocc_stream/detection"]`` (every layer's ``(B, Q, K)`` logits and ``(B, Q, 10)``
    encoded boxes, ego frame) and ``"duocc_stream/detection_classes"`` (the label id of each of the ``K`` classes),
    and ``batch.boxes`` ``(M_b, 9)`` / ``batch.box_labels`` ``(M_b,)``; ground truths whose label is not a
    detection class are left out (:func:`~occplug_duocc.blocks.queryagg.detection_targets`), and so are those farther
    than ``max_distance`` metres from the ego in x-y (the public code: 42 m; None keeps all).

    Args:
        weight: ``lambda_det`` (paper and code: 0.2).
        cls_weight, box_weight: Sparse4D's focal and L1 weights (2.0, 0.25), in the loss and the matching.
        max_distance: the ground-truth radius, metres, or None.
        reg_score_threshold: regress only the matches whose score exceeds this (the code: 0.05; None: all).
        free_label, ignore_label: unused (the model fills them in).

    Returns ``{"det_cls": scalar, "det_box": scalar}`` (summed over layers; with the detector's denoising groups
    in training also ``{"det_dn_cls", "det_dn_box"}``, :mod:`~occplug_duocc.blocks.denoising`); ``{}`` outside training
    when the batch has no boxes.
    """

    requires = frozenset({"boxes", "box_labels"})

    def __init__(
        self,
        weight: Annotated[float, NonNegative] = 0.2,
        cls_weight: Annotated[float, NonNegative] = 2.0,
        box_weight: Annotated[float, NonNegative] = 0.25,
        max_distance: Annotated[float, NonNegative] | None = None,
        reg_score_threshold: Annotated[float, UnitInterval] | None = 0.05,
        free_label: int = 17,
        ignore_label: int | None = 255,
    ) -> None:
        super().__init__()
        self.weight = float(weight)
        self.cls_weight, self.box_weight = float(cls_weight), float(box_weight)
        self.max_distance = None if max_distance is None else float(max_distance)
        self.reg_score_threshold = None if reg_score_threshold is None else float(reg_score_threshold)

    def forward(self, batch: Batch, outputs: ModelOutputs) -> dict[str, Tensor]:
        """``{"det_cls", "det_box"}`` (see the class docstring)."""
        det = outputs.extras.get(DETECTION_KEY)
        if not isinstance(det, DetectorOutput):
            raise ValueError(
                "duocc_detection: no 'duocc_stream/detection' in the model's outputs; it needs "
                "model.scene.type=duocc_stream with a query_agg mapping"
            )
        if (batch.boxes is None or batch.box_labels is None) and not self.training:
            return {}
        classes = outputs.extras[DETECTION_CLASSES_KEY]
        labels, boxes = detection_targets(batch, classes, "duocc_detection")  # type: ignore[arg-type]
        if self.max_distance is not None:
            near = [b[:, :2].norm(dim=-1) <= self.max_distance for b in boxes]
            labels = [lab[k] for lab, k in zip(labels, near, strict=True)]
            boxes = [b[k] for b, k in zip(boxes, near, strict=True)]
        device = det.cls_logits[0].device
        return detection_loss(
            det,
            [lab.to(device) for lab in labels],
            [b.to(device) for b in boxes],
            cls_weight=self.cls_weight,
            box_weight=self.box_weight,
            reg_score_threshold=self.reg_score_threshold,
        )

    @classmethod
    def conformance_outputs(cls, batch: Batch, grid: Any, channels: int) -> ModelOutputs:
        """Random two-layer detections (``Q = 8`` queries, the ten Occ3D detection classes) that require grad."""
        gen = torch.Generator().manual_seed(0)
        b = len(batch)
        logits = [torch.randn(b, 8, 10, generator=gen, requires_grad=True) for _ in range(2)]
        boxes = []
        for _ in range(2):
            enc = torch.cat(
                [
                    torch.randn(b, 8, 3, generator=gen) * 5,
                    torch.zeros(b, 8, 3),
                    torch.zeros(b, 8, 1),
                    torch.ones(b, 8, 1),
                    torch.zeros(b, 8, 2),
                ],
                -1,
            )
            boxes.append(enc.requires_grad_(True))
        det = DetectorOutput(cls_logits=logits, encoded_boxes=boxes)
        extras = {DETECTION_KEY: det, DETECTION_CLASSES_KEY: (1, 2, 3, 4, 5, 6, 7, 8, 9, 10)}
        return ModelOutputs(None, None, None, {}, lambda *a, **k: None, extras=extras)
