"""Sparse4D v3's instance denoising for DuOcc's image-to-query detector (training only).

Sparse4D v3 (Lin et al. 2023, §3.2) trains its decoder also on noised copies of the ground-truth boxes: each
copy is an extra query that starts at a noised box and must recover the box it came from (positive) or call
itself background (negative). The public DuOcc code uses it (Sparse4D v3's denoising in its config: 5 groups,
noise ``[2.0] * 3 + [0.5] * 7`` on the encoded box, at most 32 ground truths, negatives on); DuOcc's paper does
not mention it. It gives the decoder's refinement a dense, well-posed target from the first step, where the
Hungarian-matched queries give one noisy target per object.

What :func:`make_denoising_queries` builds, per sample and group (Sparse4D v3 ``SparseBox3DTarget.get_dn_anchors``):

* the first ``max_gt`` ground truths, encoded (:func:`~.matching.encode_boxes`, unknown velocity as 0);
* a positive per ground truth: the box plus noise ``u * scale``, ``u ~ U(-1, 1)`` per encoded dimension;
* with ``negatives``, a negative per ground truth: the box plus ``s * (1 + u) * scale``, ``u ~ U(0, 1)``,
  ``s = +-1`` at random, so every dimension lies 1 to 2 scales away;
* re-assignment: a Hungarian match of the group's noised boxes to its ground truths by the matching cost's box
  term (``box_weight * sum_d r_d |a_d - g_d|``, :data:`~.matching.SPARSE4D_REG_WEIGHTS`); a noised box assigned
  to a ground truth regresses it and classifies as its class, the others are background (a large positive
  noise can land nearer another object than its own). Only a sample's real queries and ground truths take part;
  the official code matches the padded ones too (zero boxes), so there a padding query can become a positive and
  a real one can be matched to a padding box and dropped.

The detector runs the groups beside its ordinary queries with an attention mask (Sparse4D v3): the ordinary
queries never see a denoising query and each group sees only itself, so the ordinary outputs are what they would
be without denoising (exactly so without dropout; in training the extra queries draw from the same random
stream); denoising queries start from zero instance features, read the temporal cache through the temporal
cross-attention as the ordinary ones do, and are left out of the temporal cache itself, the top-k merge, V2Q, DQA,
selection and evaluation. Not reproduced: Sparse4D v3's temporal denoising groups (3 of the code's 5 groups
carried to the next frame by instance id; the synthetic frames give boxes no track ids). The ground truths are
every box of a detection class in the batch: ``duocc_detection``'s ``max_distance`` (off in every recipe) does
not reach them.

Loss (:func:`denoising_loss`, per decoder layer as Sparse4D v3's head): sigmoid focal over the valid (not padding)
denoising queries, one-hot for the assigned ones and zero for background, and the weighted L1 on the assigned
ones' encoded boxes (the loss's per-dimension weights), both divided by the number of valid denoising queries
(Sparse4D v3's ``num_dn_pos``, which counts every valid one; the official code averages it over GPUs, here it is
per process as the ordinary detection loss's count is). No class-wise box weights, no score threshold on the
regression and no quality term, as in the official dn loss.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from occplug.nn import linear_assignment

from .matching import SPARSE4D_REG_WEIGHTS, encode_boxes

__all__ = ["DN_NOISE_SCALE", "DenoisingQueries", "denoising_loss", "make_denoising_queries"]

#: Sparse4D v3 / the DuOcc code's noise scale per encoded dimension (centre metres, then log size, sin, cos, vel).
DN_NOISE_SCALE = (2.0, 2.0, 2.0, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5)
_BOX_DIM = 10


@dataclass
class DenoisingQueries:
    """The noised ground truths of one training step, ``M = groups * G * (2 if negatives else 1)`` per sample.

    Group ``g`` holds queries ``[g * M_g, (g + 1) * M_g)``, ``M_g = M / groups``: its ``G`` positives, then its
    ``G`` negatives (``G`` = the batch's largest ground-truth count, at most ``max_gt``; shorter samples padded).

    Attributes:
        anchors: ``(B, M, 10)`` the noised encoded boxes the queries start at (ego frame).
        cls_target: ``(B, M)`` int64 detection class of an assigned query, -1 for background and padding.
        box_target: ``(B, M, 10)`` the assigned ground truth's encoded box (0 elsewhere; NaN where unknown).
        valid: ``(B, M)`` bool, False for padding.
        attn_mask: ``(M, M)`` bool, True where a query may not attend (another group).
        groups: number of groups.
    """

    anchors: Tensor
    cls_target: Tensor
    box_target: Tensor
    valid: Tensor
    attn_mask: Tensor
    groups: int


def make_denoising_queries(
    gt_labels: Sequence[Tensor],
    gt_boxes: Sequence[Tensor],
    groups: int,
    noise_scale: Sequence[float] = DN_NOISE_SCALE,
    max_gt: int = 32,
    negatives: bool = True,
    box_weight: float = 0.25,
    match_reg_weights: Sequence[float] = SPARSE4D_REG_WEIGHTS,
    generator: torch.Generator | None = None,
) -> DenoisingQueries | None:
    """Noised copies of the ground truths (module docstring); None when no sample has one or ``groups`` is 0.

    Args:
        gt_labels: ``B`` tensors ``(G_b,)`` int64 detection class ids.
        gt_boxes: ``B`` tensors ``(G_b, 7)`` or ``(G_b, 9)`` ``[cx, cy, cz, l, w, h, yaw(, vx, vy)]``, ego frame.
        groups: denoising groups (the code: 5).
        noise_scale: per encoded dimension (10 values).
        max_gt: ground truths used per sample (the first ones).
        negatives: add a negative per ground truth.
        box_weight, match_reg_weights: the re-assignment cost (the matching cost's box term).
        generator: a CPU random source (default torch's global one).

    Returns:
        :class:`DenoisingQueries`, or None.
    """
    if len(gt_labels) != len(gt_boxes):
        raise ValueError("make_denoising_queries: gt_labels and gt_boxes need one entry per sample")
    if len(noise_scale) != _BOX_DIM:
        raise ValueError(f"make_denoising_queries: noise_scale needs {_BOX_DIM} values, got {len(noise_scale)}")
    if any(bool((lab < 0).any()) for lab in gt_labels):
        raise ValueError("make_denoising_queries: gt_labels must be detection class ids >= 0")
    labels = [lab[:max_gt].long() for lab in gt_labels]
    boxes = [box[:max_gt] for box in gt_boxes]
    g = max((int(lab.numel()) for lab in labels), default=0)
    if groups <= 0 or g == 0:
        return None
    device = boxes[0].device
    dtype = boxes[0].dtype if boxes[0].is_floating_point() else torch.float32
    b = len(labels)
    target = torch.zeros(b, g, _BOX_DIM, dtype=dtype, device=device)
    cls = torch.full((b, g), -1, dtype=torch.int64, device=device)
    for i, (lab, box) in enumerate(zip(labels, boxes, strict=True)):
        enc = encode_boxes(box.to(dtype))
        target[i, : enc.shape[0], : enc.shape[1]] = enc
        if enc.shape[1] < _BOX_DIM:  # 7-column boxes: velocity unknown
            target[i, : enc.shape[0], enc.shape[1] :] = float("nan")
        cls[i, : lab.numel()] = lab.to(device)
    real = cls >= 0  # (B, G)
    scale = torch.tensor([float(s) for s in noise_scale], dtype=dtype, device=device)
    clean = torch.nan_to_num(target, nan=0.0)

    def rand(*shape: int) -> Tensor:
        return torch.rand(*shape, generator=generator, dtype=dtype).to(device)

    per_group = 2 * g if negatives else g
    anchors = torch.empty(b, groups, per_group, _BOX_DIM, dtype=dtype, device=device)
    anchors[:, :, :g] = clean[:, None] + (rand(b, groups, g, _BOX_DIM) * 2 - 1) * scale
    if negatives:
        sign = torch.where(rand(b, groups, g, _BOX_DIM) > 0.5, 1.0, -1.0).to(dtype)
        anchors[:, :, g:] = clean[:, None] + sign * (rand(b, groups, g, _BOX_DIM) + 1) * scale
    source = real.repeat(1, 2) if negatives else real  # (B, per_group): the query comes from a real ground truth
    cls_target = torch.full((b, groups, per_group), -1, dtype=torch.int64, device=device)
    box_target = torch.zeros(b, groups, per_group, _BOX_DIM, dtype=dtype, device=device)
    weights = torch.tensor([float(w) for w in match_reg_weights], dtype=dtype, device=device)
    for i in range(b):
        n = int(real[i].sum())
        if n == 0:
            continue
        rows = source[i].nonzero().squeeze(1)  # the sample's non-padding queries of a group
        for grp in range(groups):
            cost = box_weight * ((anchors[i, grp, rows, None] - clean[i, None, :n]).abs() * weights).sum(-1)
            qi, gi = linear_assignment(cost)
            cls_target[i, grp, rows[qi]] = cls[i, gi]
            box_target[i, grp, rows[qi]] = target[i, gi]
    m = groups * per_group
    block = torch.arange(m, device=device) // per_group
    return DenoisingQueries(
        anchors=anchors.reshape(b, m, _BOX_DIM),
        cls_target=cls_target.reshape(b, m),
        box_target=box_target.reshape(b, m, _BOX_DIM),
        valid=source[:, None].expand(b, groups, per_group).reshape(b, m),
        attn_mask=block[:, None] != block[None, :],
        groups=int(groups),
    )


def denoising_loss(
    dn: DenoisingQueries,
    cls_logits: Sequence[Tensor],
    encoded_boxes: Sequence[Tensor],
    focal,
    cls_weight: float,
    box_weight: float,
    reg_weights: Sequence[float],
    layer_weights: Sequence[float] | None = None,
) -> dict[str, Tensor]:
    """``{"det_dn_cls", "det_dn_box"}``: the denoising queries' loss summed over layers (module docstring).

    Args:
        dn: the step's :class:`DenoisingQueries`.
        cls_logits: per layer ``(B, M, K)`` the denoising queries' class logits.
        encoded_boxes: per layer ``(B, M, 10)`` their encoded boxes.
        focal: ``focal(logits, targets) -> summed loss`` (the detector's sigmoid focal, its alpha and gamma).
        cls_weight, box_weight: the detection loss's weights.
        reg_weights: per-dimension L1 weights (10).
        layer_weights: weight of each layer (default 1 each).
    """
    weights = layer_weights or [1.0] * len(cls_logits)
    norm = max(int(dn.valid.sum()), 1)
    total_cls = cls_logits[0].new_zeros(())
    total_box = cls_logits[0].new_zeros(())
    # the targets are the same for every layer: built once
    pos, valid = dn.cls_target >= 0, dn.valid
    onehot = torch.zeros_like(cls_logits[0])
    onehot[pos] = torch.nn.functional.one_hot(dn.cls_target[pos], onehot.shape[-1]).to(onehot.dtype)
    onehot = onehot[valid]
    tgt = dn.box_target.to(encoded_boxes[0].dtype)[pos]
    w = tgt.new_tensor([float(v) for v in reg_weights]) * (~tgt.isnan()).to(tgt.dtype)
    tgt = torch.nan_to_num(tgt, nan=0.0)
    for w_layer, logits, enc in zip(weights, cls_logits, encoded_boxes, strict=True):
        total_cls = total_cls + w_layer * cls_weight * focal(logits[valid], onehot) / norm
        total_box = total_box + w_layer * box_weight * ((enc[pos] - tgt).abs() * w).sum() / norm
    return {"det_dn_cls": total_cls, "det_dn_box": total_box}
