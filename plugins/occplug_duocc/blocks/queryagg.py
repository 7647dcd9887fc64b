"""DuOcc's query-guided aggregation (QueryAgg, paper §3.2, Fig. 2, Tab. 4 C / D) as one module of the stream scene.

Per frame, after StreamAgg has produced ``V_S.A`` ``(B, C, x, y, z)`` (coarse grid, current ego frame):

1. **I2Q**: :class:`~.detector.SparseDetector` reads the image encoder's levels (``outputs.image_levels``) and
   continues from the previous frame's :class:`~.detector.DetectorState` of the same batch slot; in training,
   with ``detector.num_dn_groups`` > 0 and boxes in the batch, Sparse4D v3's denoising queries of the frame's
   detection-class boxes run beside it (:mod:`.denoising`; only the detection loss reads them);
2. **selection** (suppl. A.2, :func:`~.dqa.select_queries`): in training the last layer's boxes are checked
   against the ground truth (the paper's rule by default, the public code's with ``selection: code``); with no
   ground truth (prediction, evaluation without boxes, or ``select_with_gt: false``) by score only
   (``score_threshold``, 0.3); ``gt_boxes: true`` (Tab. 4 "D with GT boxes", an evaluation ablation) replaces
   the detections by the ground-truth boxes, each carried by the query Hungarian-matched to it;
   ``gt_box_drop`` / ``gt_box_noise`` degrade that oracle (each box dropped with that probability; its
   centre moved by Gaussian noise of that std in metres along x and y, drawn from torch's global generator),
   to ask how good a detector DQA needs;
3. **V2Q** (Eq. 6, :class:`~.v2q.VoxelToQuery`): every query samples ``V_S.A`` inside its box;
4. **DQA** (Eqs. 7-10, :class:`~.dqa.DynamicQueryAggregation`): the selected queries are written into the voxels
   their boxes cover (``V_DQA`` equals ``V_S.A`` bit for bit elsewhere), then :class:`~.dqa.VoxelFFN` gives
   ``V_fin``, which the stream stores as the next frame's history.

``v2q: false, dqa: false`` is Tab. 4 C ("B + detection head"): the detector trains beside the voxels (its loss
reaches the image encoder) but nothing flows into them, ``V_fin = V_S.A``.

Classes. The detector classifies ``len(detection_classes)`` classes; ``detection_classes`` lists the label ids
(the data set's taxonomy, as ``batch.box_labels``) of the detection classes in order, default the Occ3D
dynamic classes ``1..10`` (barrier ... truck, the nuScenes detection classes), so detection class ``i`` is label
``detection_classes[i]``; ground-truth boxes of other labels are ignored (:func:`detection_targets`).

Assumptions where the paper is silent (code notes §3): V2Q runs once, after the detector's last layer (the code:
inside layer 6, before its last refinement: the detector's ``v2q_placement``), so the boxes DQA uses are the last
layer's; the paper's small-object
rule needs a "small" set, here the classes ``small_classes`` (default ``small_objects``: the run's classes named
barrier, bicycle, motorcycle, pedestrian and traffic cone, by name).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import torch
from torch import Tensor, nn

from occplug.config import settings
from occplug.constraints import LabelIds, Length, NonNegative, Positive, Range, UnitInterval
from occplug.data import OCC3D_CLASSES, Batch, class_groups
from occplug.geometry import GridSpec

from .boxes import decode_boxes
from .denoising import DN_NOISE_SCALE
from .detector import DetectorOutput, DetectorState, SparseDetector
from .dqa import CODE_SELECTION, PAPER_SELECTION, DynamicQueryAggregation, VoxelFFN, select_queries
from .matching import encode_boxes, hungarian_match
from .v2q import VoxelToQuery

__all__ = [
    "DEFAULT_DETECTION_CLASSES",
    "DETECTION_GROUP",
    "DEFAULT_SMALL_CLASSES",
    "SMALL_OBJECT_NAMES",
    "small_object_ids",
    "DetectorSettings",
    "QueryAggOutput",
    "QueryAggSettings",
    "QueryAggregation",
    "SelectionSettings",
    "detection_targets",
    "resolve_detection_classes",
]

#: The class group whose label ids are the detection classes when ``detection_classes`` is left out
#: (:func:`occplug.data.class_groups`; Occ3D's: barrier ... truck, the nuScenes detection set).
DETECTION_GROUP = "dynamic"
#: Occ3D label ids of the detection classes (Occ3D's ``dynamic`` group, by name: 1 to 10): what a QueryAgg built
#: without the run's class names detects.
DEFAULT_DETECTION_CLASSES: tuple[int, ...] = class_groups(OCC3D_CLASSES)[DETECTION_GROUP]
#: The class names the paper's selection treats as small objects (cost test) when ``small_classes`` is
#: ``small_objects``: resolved against the run's class names (those a taxonomy lacks are left out).
#: Occ3D's five (the paper's taxonomy) and SemanticKITTI's riders and persons.
SMALL_OBJECT_NAMES: tuple[str, ...] = (
    "barrier",
    "bicycle",
    "motorcycle",
    "pedestrian",
    "traffic_cone",
    "person",
    "bicyclist",
    "motorcyclist",
)


def small_object_ids(class_names: Sequence[str]) -> tuple[int, ...]:
    """The label ids of ``class_names`` named in :data:`SMALL_OBJECT_NAMES`, in id order."""
    return tuple(i for i, name in enumerate(class_names) if name in SMALL_OBJECT_NAMES)


#: The label ids :data:`SMALL_OBJECT_NAMES` name in Occ3D's classes (and the synthetic world's): 1, 2, 6, 7, 8.
DEFAULT_SMALL_CLASSES: tuple[int, ...] = small_object_ids(OCC3D_CLASSES)
#: A score threshold: sigmoid scores lie in (0, 1), so at 1 or above no query is ever selected (negative: all are).
_SCORE_THRESHOLD = Range(high=1.0, high_open=True)


@settings
class SelectionSettings:
    """``query_agg.selection`` given as a mapping: :func:`~.dqa.select_queries`' training thresholds.

    Each threshold left out is the paper's (:data:`~.dqa.PAPER_SELECTION`). ``small_classes`` are detection class
    indices here (positions in ``detection_classes``), ``null`` for no small / large split (either test admits a
    query, the public code's rule); left out, the small set is ``query_agg.small_classes``.
    """

    score_threshold: Annotated[float, _SCORE_THRESHOLD] = PAPER_SELECTION["score_threshold"]
    iou_threshold: Annotated[float, Range(high=1.0, high_open=True)] | None = PAPER_SELECTION["iou_threshold"]
    cost_threshold: Annotated[float, Positive] | None = PAPER_SELECTION["cost_threshold"]
    center_weight: Annotated[float, NonNegative] = PAPER_SELECTION["center_weight"]
    size_weight: Annotated[float, NonNegative] = PAPER_SELECTION["size_weight"]
    small_classes: Literal["query_agg"] | tuple[Annotated[int, NonNegative], ...] | None = "query_agg"
    small_size: Annotated[float, Positive] | None = None


@settings
class DetectorSettings:
    """``query_agg.detector``: the image-to-query detector's settings (:class:`~.detector.SparseDetector`).

    The detector's other arguments come from what the scene is given: ``num_classes`` is
    ``len(detection_classes)`` and ``level_channels`` the image encoder's levels' channels. ``anchor_range``
    left out (``null``) is the scene's grid range. The defaults are :class:`~.detector.SparseDetector`'s.
    """

    channels: Annotated[int, Positive] = 64
    num_queries: Annotated[int, Positive] = 64
    num_layers: Annotated[int, Positive] = 2
    num_temporal: Annotated[int, NonNegative] = 32
    heads: Annotated[int, Positive] = 4
    groups: Annotated[int, Positive] = 4
    num_learnable_points: Annotated[int, NonNegative] = 6
    anchor_range: Annotated[tuple[float, ...], Length(exact=6)] | None = None
    anchor_size: Annotated[tuple[Annotated[float, Positive], ...], Length(exact=3)] = (4.0, 1.8, 1.6)
    anchor_centres: tuple[Annotated[tuple[float, ...], Length(exact=3)], ...] | None = None
    learn_instance_feature: bool = True
    confidence_decay: Annotated[float, UnitInterval] = 0.6
    use_velocity: bool = True
    max_time_interval: Annotated[float, Positive] = 2.0
    dropout: Annotated[float, Range(low=0.0, high=1.0, high_open=True)] = 0.1
    num_dn_groups: Annotated[int, NonNegative] = 0
    dn_noise_scale: Annotated[tuple[Annotated[float, NonNegative], ...], Length(exact=10)] = DN_NOISE_SCALE
    max_dn_gt: Annotated[int, Positive] = 32
    dn_negatives: bool = True
    checkpoint_aggregation: bool = False
    v2q_placement: Literal["after_last_refinement", "before_last_refinement"] = "after_last_refinement"


@settings
class QueryAggSettings:
    """``duocc_stream``'s ``query_agg``: QueryAgg's settings (module docstring).

    Attributes:
        v2q, dqa: V2Q into ``V_S.A`` and DQA on the selected queries (both off: Tab. 4 C, the detector alone);
            V2Q needs DQA.
        gt_boxes: DQA reads the ground-truth boxes (Tab. 4 "D with GT boxes", an evaluation ablation);
            ``gt_box_drop`` (probability) / ``gt_box_noise`` (metres, std of the centre in x and y) degrade them.
        select_with_gt: select by the ground truth in training (else by score only).
        selection: ``paper`` (suppl. A.2), ``code`` (the public code's rule) or a mapping
            (:class:`SelectionSettings`).
        small_classes: label ids the paper's rule treats as small objects (only those among ``detection_classes``),
            or ``small_objects``: the run's classes named in :data:`SMALL_OBJECT_NAMES`, by name
            (:func:`resolve_detection_classes`; Occ3D and the synthetic world: 1, 2, 6, 7, 8).
        score_threshold: selection without ground truth (evaluation, prediction): ``score > score_threshold``.
        max_queries: keep at most this many selected queries per sample (None: all).
        detection_classes: label id of each detection class, in order (None: the run's ``dynamic`` class group,
            by name, :func:`resolve_detection_classes`; Occ3D and the synthetic world: 1 to 10).
        detector: the detector's settings (:class:`DetectorSettings`).
        v2q_heads, v2q_points: V2Q's attention heads and sampling points per head.
        dqa_heads, coverage, positional: DQA's heads, which voxels a box covers (``center``: the voxel centre
            inside the rotated box, Eq. 10; ``aabb``: the public code) and its positional encoding.
        ffn_hidden: the voxel FFN's hidden width (None: 4 x the scene's channels).
        write: what DQA writes into a selected box's voxels: ``instance``, the query's features (after V2Q; the
            paper), or ``class``, a learned embedding of the box's class (the ground truth's with ``gt_boxes``, else
            the detector's top class) with V2Q off: a footprint input that carries no instance features, the
            control of the ground-truth-box oracle (the difference between the two is what instance features add), or
            ``constant``, one learned embedding for every selected box (no class, no instance feature; V2Q off): with
            ``gt_boxes`` the footprints alone, the real control of the oracle (``class`` carries the ground-truth class
            too, so it holds more ground truth than the oracle's instance queries).
        dqa_output_bias, dqa_instance_norm, outside_boxes, empty_selection, positional_order: DQA's switches to the
            public code's behaviour (:class:`~.dqa.DynamicQueryAggregation` ``output_bias``, ``instance_norm``,
            ``outside_boxes``, ``empty_selection``, ``positional_order``).
        box_rotation: DQA's and V2Q's box rotation: ``yaw`` or the detector's raw ``sin_cos`` (the public code; the
            ground truth's ``(sin yaw, cos yaw)`` with ``gt_boxes``).
        v2q_offset_input, v2q_value_bias, v2q_fixed_key_points: V2Q's switches (:class:`~.v2q.VoxelToQuery`
            ``offset_input``, ``value_bias``, ``fixed_key_points``); where V2Q runs is the detector's
            ``v2q_placement``.
    """

    v2q: bool = True
    dqa: bool = True
    gt_boxes: bool = False
    gt_box_drop: Annotated[float, UnitInterval] = 0.0
    gt_box_noise: Annotated[float, NonNegative] = 0.0
    select_with_gt: bool = True
    selection: Literal["paper", "code"] | SelectionSettings = "paper"
    small_classes: Literal["small_objects"] | Annotated[tuple[Annotated[int, NonNegative], ...], LabelIds()] | None = (
        "small_objects"
    )
    score_threshold: Annotated[float, _SCORE_THRESHOLD] = 0.3
    max_queries: Annotated[int, Positive] | None = None
    detection_classes: Annotated[tuple[Annotated[int, NonNegative], ...], Length(min=1), LabelIds()] | None = None
    detector: DetectorSettings = DetectorSettings()
    v2q_heads: Annotated[int, Positive] = 4
    v2q_points: Annotated[int, Positive] = 6
    dqa_heads: Annotated[int, Positive] = 4
    coverage: Literal["center", "aabb"] = "center"
    positional: bool = True
    ffn_hidden: Annotated[int, Positive] | None = None
    write: Literal["instance", "class", "constant"] = "instance"
    dqa_output_bias: bool = False
    dqa_instance_norm: bool = False
    outside_boxes: Literal["skip", "clamp"] = "skip"
    empty_selection: Literal["skip", "dummy_query"] = "skip"
    positional_order: Literal["xyz", "yxz"] = "xyz"
    box_rotation: Literal["yaw", "sin_cos"] = "yaw"
    v2q_offset_input: Literal["feature_and_anchor", "feature"] = "feature_and_anchor"
    v2q_value_bias: bool = False
    v2q_fixed_key_points: bool = False


def resolve_detection_classes(config: QueryAggSettings, class_names: Sequence[str] | None) -> QueryAggSettings:
    """``config`` with its detection (and small) classes checked against, or taken from, the run's class names.

    Left out (None), the detection classes are the label ids of the run's :data:`DETECTION_GROUP` class group
    (:func:`occplug.data.class_groups`, by name); given, each must be a label id of the run's classes.
    ``small_classes: small_objects`` becomes the ids of the run's classes named in :data:`SMALL_OBJECT_NAMES`.
    Without class names (a QueryAgg built outside a run) the detection classes are returned as they are and the
    small objects are Occ3D's (:data:`DEFAULT_SMALL_CLASSES`).

    Raises:
        ValueError: an id the run's classes do not have, no class group to take them from, or ``small_objects``
            naming none of the run's classes (one line).
    """
    if class_names is None:
        if config.small_classes == "small_objects":
            config = dataclasses.replace(config, small_classes=DEFAULT_SMALL_CLASSES)
        return config
    key = "duocc_stream query_agg.detection_classes"
    if config.detection_classes is None:
        groups = class_groups(tuple(class_names))
        if groups is None or not groups.get(DETECTION_GROUP):
            raise ValueError(
                f"{key}: the run's {len(class_names)} classes are no taxonomy with a '{DETECTION_GROUP}' class group "
                "(occplug.data.class_groups); list the detection classes' label ids"
            )
        config = dataclasses.replace(config, detection_classes=groups[DETECTION_GROUP])
    for label in config.detection_classes:
        if not 0 <= int(label) < len(class_names):
            raise ValueError(
                f"{key}: label id {label} is not one of the run's {len(class_names)} classes (0 to {len(class_names) - 1})"
            )
    if config.small_classes == "small_objects":
        small = small_object_ids(class_names)
        if not small:
            raise ValueError(
                f"duocc_stream query_agg.small_classes: small_objects names none of the run's {len(class_names)} "
                f"classes ({', '.join(SMALL_OBJECT_NAMES)}); list the small classes' label ids, or null for no "
                "small / large split"
            )
        config = dataclasses.replace(config, small_classes=small)
    return config


def detection_targets(batch: Batch, classes: Sequence[int], who: str) -> tuple[list[Tensor], list[Tensor]]:
    """Ground-truth boxes of the detection classes, labels mapped to detection class ids.

    Args:
        batch: reads ``boxes`` (``B`` tensors ``(M_b, 9)``, ego frame) and ``box_labels`` (``B`` tensors ``(M_b,)``
            label ids).
        classes: label id of each detection class (``classes[i]`` is detection class ``i``).
        who: named in the error when the batch has no boxes.

    Returns:
        ``(labels, boxes)``: ``B`` tensors ``(G_b,)`` int64 detection class ids and ``(G_b, 9)`` boxes
        ``[cx, cy, cz, l, w, h, yaw, vx, vy]`` (ego frame), only the boxes whose label is a detection class.
    """
    batch.require("boxes", "box_labels", by=who)
    lookup = torch.full((max(max(classes), 0) + 1,), -1, dtype=torch.int64)
    lookup[torch.as_tensor(list(classes), dtype=torch.int64)] = torch.arange(len(classes))
    labels, boxes = [], []
    for lab, box in zip(batch.box_labels, batch.boxes, strict=True):
        lab = lab.long()
        ids = torch.where(
            (lab >= 0) & (lab < lookup.numel()), lookup.to(lab.device)[lab.clamp(0, lookup.numel() - 1)], -1
        )
        keep = ids >= 0
        labels.append(ids[keep])
        boxes.append(box[keep])
    return labels, boxes


def _selection_rule(selection: str | SelectionSettings, small: list[int]) -> dict[str, Any]:
    """``select_queries`` keyword arguments of ``paper`` / ``code`` / :class:`SelectionSettings`."""
    if selection == "code":
        return dict(CODE_SELECTION)
    if selection == "paper":
        return {**PAPER_SELECTION, "small_classes": small}
    rule = dataclasses.asdict(selection)
    if rule["small_classes"] == "query_agg":
        rule["small_classes"] = small
    return rule


@dataclass
class QueryAggOutput:
    """What :class:`QueryAggregation` returns for one frame.

    Attributes:
        volume: ``V_fin`` ``(B, C, x, y, z)`` (``V_S.A`` itself when DQA is off), current ego frame.
        v_dqa: ``V_DQA`` ``(B, C, x, y, z)`` before the FFN, or None without DQA.
        detection: the detector's output (``Q`` queries per layer, boxes in the current ego frame).
        selected: ``(B, Q)`` bool, the queries DQA wrote (all False without DQA).
        boxes: ``(B, Q, 9)`` the boxes V2Q / DQA used (the last layer's, or the ground truth with ``gt_boxes``).
        state: the detector state to keep for the next frame (``anchors (B, k, 10)``, ``features (B, k, C_q)``,
            ``confidence (B, k)``), or None (``num_temporal: 0``).
    """

    volume: Tensor
    v_dqa: Tensor | None
    detection: DetectorOutput
    selected: Tensor
    boxes: Tensor
    state: dict[str, Tensor] | None


class QueryAggregation(nn.Module):
    """I2Q, V2Q, DQA and the FFN on one frame (module docstring).

    Args:
        channels: ``C`` of ``V_S.A``.
        grid: the coarse grid of ``V_S.A`` (ego frame).
        level_channels: the image levels' channels, finest first (the image encoder's ``level_channels``).
        config: QueryAgg's settings (validated by the config's validator).

    Raises:
        ValueError: settings that contradict each other (one line).
    """

    def __init__(
        self, channels: int, grid: GridSpec, level_channels: Sequence[int], config: QueryAggSettings | None = None
    ) -> None:
        super().__init__()
        cfg = QueryAggSettings() if config is None else config
        self.grid = grid
        self.v2q_on, self.dqa_on = bool(cfg.v2q), bool(cfg.dqa)
        if self.v2q_on and not self.dqa_on:
            raise ValueError(
                "duocc_stream query_agg: v2q: true needs dqa: true (V2Q runs after the detector's last layer here, "
                "so without DQA nothing reads its output); the detector alone is v2q: false, dqa: false"
            )
        self.gt_boxes, self.select_with_gt = bool(cfg.gt_boxes), bool(cfg.select_with_gt)
        self.gt_box_drop, self.gt_box_noise = float(cfg.gt_box_drop), float(cfg.gt_box_noise)
        if (self.gt_box_drop or self.gt_box_noise) and not self.gt_boxes:
            raise ValueError(
                "duocc_stream query_agg.gt_box_drop / gt_box_noise degrade the ground-truth boxes: they need gt_boxes: true"
            )
        self.classes = tuple(int(c) for c in (cfg.detection_classes or DEFAULT_DETECTION_CLASSES))
        small = DEFAULT_SMALL_CLASSES if cfg.small_classes == "small_objects" else cfg.small_classes  # outside a run
        small_ids = [self.classes.index(int(c)) for c in (small or []) if int(c) in self.classes]
        self.rule = _selection_rule(cfg.selection, small_ids)
        self.score_threshold = float(cfg.score_threshold)
        self.max_queries = None if cfg.max_queries is None else int(cfg.max_queries)
        det = dataclasses.asdict(cfg.detector)
        if det["anchor_range"] is None:
            det["anchor_range"] = tuple(grid.range)
        self.detector = SparseDetector(
            num_classes=len(self.classes), level_channels=[int(c) for c in level_channels], **det
        )
        q = self.detector.channels
        self.v2q = (
            VoxelToQuery(
                q,
                grid,
                volume_channels=channels,
                heads=cfg.v2q_heads,
                points=cfg.v2q_points,
                offset_input=cfg.v2q_offset_input,
                value_bias=cfg.v2q_value_bias,
                fixed_key_points=cfg.v2q_fixed_key_points,
                box_rotation=cfg.box_rotation,
            )
            if self.v2q_on
            else None
        )
        self.write, self.box_rotation = cfg.write, cfg.box_rotation
        if self.write != "instance" and not self.dqa_on:
            raise ValueError(f"duocc_stream query_agg.write: {self.write} is what DQA writes: it needs dqa: true")
        if self.write != "instance":  # a footprint (of the box's class, or constant): no instance features, no V2Q
            self.v2q = None
        self.class_embed = nn.Embedding(len(self.classes), q) if self.write == "class" else None
        #: ``(q,)`` what every selected box writes with ``write: constant``
        self.constant_embed = nn.Parameter(torch.randn(q)) if self.write == "constant" else None
        self.dqa = None
        self.ffn = None
        if self.dqa_on:
            self.dqa = DynamicQueryAggregation(
                channels,
                grid,
                query_channels=q,
                heads=cfg.dqa_heads,
                coverage=cfg.coverage,
                positional=cfg.positional,
                output_bias=cfg.dqa_output_bias,
                instance_norm=cfg.dqa_instance_norm,
                outside_boxes=cfg.outside_boxes,
                empty_selection=cfg.empty_selection,
                box_rotation=cfg.box_rotation,
                positional_order=cfg.positional_order,
            )
            self.ffn = VoxelFFN(channels, cfg.ffn_hidden)

    # ------------------------------------------------------------------ state
    def state_template(self, batch: Batch, device: torch.device) -> dict[str, Tensor] | None:
        """A zero state ``{anchors (B, k, 10), features (B, k, C_q), confidence (B, k)}`` (what a reset slot
        reads: the detector ignores it there), or None when nothing is propagated."""
        k = self.detector.num_temporal
        if k == 0:
            return None
        b = len(batch)
        return {
            "anchors": torch.zeros(b, k, 10, device=device),
            "features": torch.zeros(b, k, self.detector.channels, device=device),
            "confidence": torch.zeros(b, k, device=device),
        }

    # ------------------------------------------------------------------ selection
    def _select(self, det: DetectorOutput, batch: Batch) -> tuple[Tensor, Tensor, Tensor]:
        """``(selected (B, Q) bool, boxes (B, Q, 9), classes (B, Q) int64)`` for V2Q / DQA (module docstring, step
        2); ``classes``: each query's detection class (the matched ground truth's with ``gt_boxes``, else its top
        class)."""
        logits, boxes = det.cls_logits[-1], det.boxes[-1]
        scores = logits.detach().sigmoid().amax(-1)
        classes = logits.detach().argmax(-1)
        has_gt = batch.boxes is not None and batch.box_labels is not None
        if self.gt_boxes:
            if not has_gt:
                raise ValueError("duocc_stream query_agg.gt_boxes: true needs batch.boxes and batch.box_labels")
            labels, gts = detection_targets(batch, self.classes, "duocc_stream query_agg.gt_boxes")
            matches = hungarian_match(logits, det.encoded_boxes[-1], labels, [encode_boxes(g.to(boxes)) for g in gts])
            selected = torch.zeros_like(scores, dtype=torch.bool)
            boxes = boxes.detach().clone()
            classes = classes.clone()
            for b, (qi, gi) in enumerate(matches):
                classes[b, qi] = labels[b][gi].to(classes)
                box = gts[b][gi].to(boxes)
                if self.gt_box_noise > 0:
                    box[:, :2] = box[:, :2] + self.gt_box_noise * torch.randn(box.shape[0], 2).to(box)
                if self.gt_box_drop > 0:
                    keep = torch.rand(box.shape[0]) >= self.gt_box_drop
                    qi, box = qi[keep.to(qi.device)], box[keep.to(box.device)]
                selected[b, qi] = True
                boxes[b, qi] = box
            return selected, boxes, classes
        if self.training and self.select_with_gt and has_gt:
            _, gts = detection_targets(batch, self.classes, "duocc_stream query_agg")
            selected = select_queries(
                scores,
                boxes.detach(),
                logits.detach().argmax(-1),
                gt_boxes=[g.to(boxes) for g in gts],
                max_queries=self.max_queries,
                **self.rule,
            )
        else:
            selected = select_queries(
                scores, boxes.detach(), score_threshold=self.score_threshold, max_queries=self.max_queries
            )
        return selected, boxes, classes

    def _rotation_boxes(self, encoded: Tensor) -> Tensor:
        """``(B, Q, 10)`` encoded boxes -> V2Q's boxes: decoded (yaw) or ``[cx, cy, cz, l, w, h, sin, cos]``."""
        if self.box_rotation == "sin_cos":
            return torch.cat([encoded[..., :3], encoded[..., 3:6].exp(), encoded[..., 6:8]], -1)
        return decode_boxes(encoded)

    # ------------------------------------------------------------------ forward
    def forward(
        self,
        volume: Tensor,
        levels: Sequence[Tensor],
        batch: Batch,
        state: dict[str, Tensor] | None,
        reset: Tensor,
        prev_to_current: Tensor,
        dt: Tensor,
    ) -> QueryAggOutput:
        """One frame of QueryAgg.

        Args:
            volume: ``V_S.A`` ``(B, C, x, y, z)`` on :attr:`grid`, current ego frame.
            levels: the image encoder's levels, ``(B, N, C_l, H_l, W_l)`` each, finest first.
            batch: the frames (cameras, images, ``boxes`` / ``box_labels`` where selection or ``gt_boxes`` use them).
            state: the previous frame's detector state per slot (:meth:`state_template` layout, the previous ego
                frame), or None.
            reset: ``(B,)`` bool, slots whose state must not be used.
            prev_to_current: ``(B, 4, 4)`` float64 previous ego -> current ego (identity where reset).
            dt: ``(B,)`` float64 seconds since the stored frame (0 where reset).

        Returns:
            :class:`QueryAggOutput`.
        """
        det_state = None
        pose = batch.ego_to_global.to(torch.float64)
        if state is not None:
            # the stream gives the previous frame relative to this one: pose and time of the stored frame
            det_state = DetectorState(
                anchors=state["anchors"],
                features=state["features"],
                confidence=state["confidence"],
                ego_to_global=pose @ prev_to_current.to(pose),
                timestamp=batch.timestamp.to(torch.float64) - dt.to(torch.float64),
            )
        denoising = None
        if (
            self.training
            and self.detector.num_dn_groups > 0
            and batch.boxes is not None
            and batch.box_labels is not None
        ):
            labels, gts = detection_targets(batch, self.classes, "duocc_stream query_agg")
            denoising = self.detector.denoising_queries(
                [lab.to(volume.device) for lab in labels],
                [g.to(device=volume.device, dtype=self.detector.anchors.dtype) for g in gts],
            )
        inside = None
        if self.v2q is not None and self.detector.v2q_placement == "before_last_refinement":
            v2q = self.v2q

            def inside(x: Tensor, anchors: Tensor, embed: Tensor) -> Tensor:
                return v2q(volume, x, self._rotation_boxes(anchors), embed)

        h, w = batch.images.shape[-2:]
        det = self.detector(
            list(levels),
            (int(h), int(w)),
            batch.intrinsics,
            batch.cam_to_ego,
            batch.img_aug,
            state=det_state,
            ego_to_global=pose,
            timestamp=batch.timestamp,
            reset=reset,
            denoising=denoising,
            v2q=inside,
        )
        new_state = None
        if det.state is not None:
            new_state = {
                "anchors": det.state.anchors,
                "features": det.state.features,
                "confidence": det.state.confidence,
            }
        if not self.dqa_on and not self.v2q_on:  # Tab. 4 C: the detector only
            none = torch.zeros(det.features.shape[:2], dtype=torch.bool, device=volume.device)
            return QueryAggOutput(volume, None, det, none, det.boxes[-1], new_state)
        selected, boxes, classes = self._select(det, batch)
        queries = det.features
        if self.class_embed is not None:
            queries = self.class_embed(classes)
        elif self.constant_embed is not None:
            queries = self.constant_embed.expand(*classes.shape, -1)
        rot = boxes
        if self.box_rotation == "sin_cos":  # the detector's raw (sin, cos); the ground truth's from its yaw
            raw = det.encoded_boxes[-1][..., 6:8]
            if self.gt_boxes:
                raw = torch.stack([boxes[..., 6].sin(), boxes[..., 6].cos()], -1)
            rot = torch.cat([boxes[..., :6], raw], -1)
        if self.v2q is not None and inside is None:
            queries = self.v2q(volume, queries, rot, det.anchor_embed)
        assert self.dqa is not None and self.ffn is not None
        v_dqa = self.dqa(volume, queries, rot, selected)
        return QueryAggOutput(self.ffn(v_dqa), v_dqa, det, selected, boxes, new_state)
