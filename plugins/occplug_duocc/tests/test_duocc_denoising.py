"""Sparse4D v3's instance denoising in DuOcc's detector: the noised queries, their re-assignment, the attention
mask that keeps them from the ordinary queries, and their loss."""

import itertools

import pytest
import torch
from test_duocc_detector import GT_BOX, H, W, _cameras, _detector, _levels, _pose

from occplug.nn import sigmoid_focal_loss
from occplug.run import runner
from occplug_duocc.blocks.denoising import DN_NOISE_SCALE, denoising_loss, make_denoising_queries
from occplug_duocc.blocks.detection_loss import detection_loss
from occplug_duocc.blocks.detector import SparseDetector, _DecoderLayer
from occplug_duocc.blocks.matching import SPARSE4D_REG_WEIGHTS, encode_boxes

SCALE = torch.tensor(DN_NOISE_SCALE)


def _boxes(*centres):
    return torch.tensor([[x, y, 0.5, 4.0, 1.8, 1.6, 0.3, 1.0, -0.5] for x, y in centres])


def test_queries_layout_noise_bounds_padding_and_group_mask():
    gen = torch.Generator().manual_seed(0)
    labels = [torch.tensor([0, 2, 1]), torch.tensor([1])]
    boxes = [_boxes((5.0, 0.0), (20.0, 5.0), (-10.0, -8.0)), _boxes((3.0, 3.0))]
    dn = make_denoising_queries(labels, boxes, groups=2, generator=gen)
    assert dn is not None and dn.groups == 2
    assert dn.anchors.shape == dn.box_target.shape == (2, 12, 10)  # 2 groups x (3 positives + 3 negatives)
    # group layout: positives then negatives of the batch's 3 slots; sample 1 has one real ground truth
    assert dn.valid[0].all()
    assert dn.valid[1].tolist() == [True, False, False, True, False, False] * 2
    enc = [encode_boxes(b) for b in boxes]
    for i, e in enumerate(enc):
        n = e.shape[0]
        for g in range(2):
            pos = dn.anchors[i, g * 6 : g * 6 + n]
            neg = dn.anchors[i, g * 6 + 3 : g * 6 + 3 + n]
            assert ((pos - e).abs() <= SCALE + 1e-5).all()  # U(-1, 1) x scale
            off = (neg - e).abs()
            assert ((off >= SCALE - 1e-5) & (off <= 2 * SCALE + 1e-5)).all()  # 1 to 2 scales away
            # every ground truth is assigned to exactly one query of the group, with its class and box
            cls = dn.cls_target[i, g * 6 : (g + 1) * 6]
            assert sorted(cls[cls >= 0].tolist()) == sorted(labels[i].tolist())
            for q in (cls >= 0).nonzero().squeeze(1).tolist():  # the class's own box (labels are distinct here)
                j = labels[i].tolist().index(int(cls[q]))
                torch.testing.assert_close(dn.box_target[i, g * 6 + q], e[j])
    assert (dn.cls_target[~dn.valid] == -1).all()
    expected = torch.block_diag(torch.ones(6, 6), torch.ones(6, 6)) == 0
    assert torch.equal(dn.attn_mask, expected)


def test_reassignment_is_the_minimum_cost_assignment_of_each_group():
    gen = torch.Generator().manual_seed(3)
    # three boxes within a metre: large noise often lands a query nearer another box than its own
    boxes = [_boxes((5.0, 0.0), (5.6, 0.4), (4.5, -0.5))]
    dn = make_denoising_queries([torch.tensor([0, 1, 2])], boxes, groups=4, generator=gen)
    target = encode_boxes(boxes[0])
    w = torch.tensor(SPARSE4D_REG_WEIGHTS)
    swapped = 0
    for g in range(4):
        anchors = dn.anchors[0, g * 6 : (g + 1) * 6]
        cost = 0.25 * ((anchors[:, None] - target[None]).abs() * w).sum(-1)  # (6 queries, 3 boxes)
        best = min(sum(cost[q, j] for j, q in enumerate(p)) for p in itertools.permutations(range(6), 3))
        cls = dn.cls_target[0, g * 6 : (g + 1) * 6]
        chosen = sum(cost[q, int(cls[q])] for q in range(6) if cls[q] >= 0)  # label j is box j here
        torch.testing.assert_close(chosen, best)
        swapped += int((cls[:3] != torch.arange(3)).any())
    assert swapped > 0  # the example does exercise the re-assignment


def test_no_ground_truth_or_no_group_gives_no_queries():
    empty = [torch.zeros(0, dtype=torch.long)]
    assert make_denoising_queries(empty, [torch.zeros(0, 9)], groups=5) is None
    assert make_denoising_queries([torch.tensor([1])], [GT_BOX], groups=0) is None
    with pytest.raises(ValueError, match="noise_scale needs 10"):
        make_denoising_queries([torch.tensor([1])], [GT_BOX], groups=1, noise_scale=[1.0])


def test_seven_column_boxes_leave_velocity_unknown_and_max_gt_cuts():
    dn = make_denoising_queries([torch.tensor([0, 1, 2])], [_boxes((1, 1), (2, 2), (3, 3))[:, :7]], 1, max_gt=2)
    assert dn.anchors.shape == (1, 4, 10)  # two ground truths kept
    assigned = dn.cls_target[0] >= 0
    assert dn.box_target[0, assigned, 8:].isnan().all() and not dn.anchors.isnan().any()


def test_the_ordinary_queries_are_unchanged_by_denoising_queries_beside_them(monkeypatch):
    """The attention mask keeps every ordinary output (logits, boxes, features, the state) as without denoising,
    on a first frame and on a second one that reads the propagated state."""
    torch.manual_seed(0)
    det = _detector(num_dn_groups=2)
    k, c2e, a = _cameras(b=2, n=2)
    gen = torch.Generator().manual_seed(1)
    dn = det.denoising_queries(
        [torch.tensor([0, 2]), torch.tensor([1])], [_boxes((8, 1), (12, -3)), _boxes((6, 2))], generator=gen
    )
    kw = {"ego_to_global": _pose(b=2), "timestamp": torch.zeros(2, dtype=torch.float64)}
    plain = det(_levels(2, 2), (H, W), k, c2e, a, **kw)
    with_dn = det(_levels(2, 2), (H, W), k, c2e, a, denoising=dn, **kw)
    assert with_dn.dn_cls_logits[0].shape == (2, 8, 3) and with_dn.dn_encoded_boxes[-1].shape == (2, 8, 10)
    assert plain.dn_cls_logits is None and plain.denoising is None

    def same(x, y):
        for u, v in zip(x.cls_logits + x.encoded_boxes, y.cls_logits + y.encoded_boxes, strict=True):
            torch.testing.assert_close(u, v, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(x.features, y.features, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(x.state.anchors, y.state.anchors, atol=1e-5, rtol=1e-5)

    same(plain, with_dn)
    kw2 = {"ego_to_global": _pose(t=(1.0, 0.0, 0.0), b=2), "timestamp": torch.full((2,), 0.5, dtype=torch.float64)}
    second = det(_levels(2, 2, seed=1), (H, W), k, c2e, a, state=plain.state, **kw2)
    second_dn = det(_levels(2, 2, seed=1), (H, W), k, c2e, a, state=plain.state, denoising=dn, **kw2)
    same(second, second_dn)
    # and the other way: a group's outputs depend on neither the ordinary queries (their anchors and learned
    # features) nor the other groups' anchors; the denoising queries start from zero features
    moved = type(dn)(dn.anchors.clone(), dn.cls_target, dn.box_target, dn.valid, dn.attn_mask, dn.groups)
    moved.anchors[:, 4:, :3] += 3.0  # group 1 of 2 (4 queries each)
    with torch.no_grad():
        det.anchors[:, :3] += 1.0
        det.instance_feature += 0.5
    other = det(_levels(2, 2, seed=1), (H, W), k, c2e, a, state=plain.state, denoising=moved, **kw2)
    before = second_dn.dn_cls_logits + second_dn.dn_encoded_boxes
    for u, v in zip(before, other.dn_cls_logits + other.dn_encoded_boxes, strict=True):
        torch.testing.assert_close(u[:, :4], v[:, :4], atol=1e-5, rtol=1e-5)  # group 0 unchanged
        assert not torch.allclose(u[:, 4:], v[:, 4:], atol=1e-3)  # group 1 moved
    # without the mask the denoising queries would leak into the ordinary ones through self-attention
    forward = _DecoderLayer.forward
    monkeypatch.setattr(_DecoderLayer, "forward", lambda self, *args: forward(self, *args[:5], None))
    leaky = det(_levels(2, 2, seed=1), (H, W), k, c2e, a, state=plain.state, denoising=dn, **kw2)
    assert not torch.allclose(second.cls_logits[-1], leaky.cls_logits[-1], atol=1e-3)


def test_denoising_loss_prefers_recovered_boxes_and_trains_the_detector():
    torch.manual_seed(0)
    det = _detector(num_dn_groups=2, dropout=0.0)
    k, c2e, a = _cameras()
    levels = _levels(seed=3)
    labels, gts = [torch.tensor([1])], [GT_BOX]
    dn = det.denoising_queries(labels, gts, generator=torch.Generator().manual_seed(0))
    out = det(levels, (H, W), k, c2e, a, denoising=dn)
    loss = detection_loss(out, labels, gts)
    assert {"det_cls", "det_box", "det_dn_cls", "det_dn_box"} == set(loss)
    # a perfect denoising output: the assigned queries at their boxes with their class, the rest background
    perfect = [torch.full((*dn.cls_target.shape, 3), -10.0)]
    pos = dn.cls_target >= 0
    perfect[0][pos, dn.cls_target[pos]] = 10.0
    box = torch.nan_to_num(dn.box_target, nan=0.0)
    out_perfect = type(out)(
        out.cls_logits[-1:], out.encoded_boxes[-1:], denoising=dn, dn_cls_logits=perfect, dn_encoded_boxes=[box]
    )
    ideal = detection_loss(out_perfect, labels, gts)
    assert ideal["det_dn_box"] == 0 and ideal["det_dn_cls"] < 1e-6
    # the denoising loss alone reaches the detector and falls when fitted
    opt = torch.optim.Adam(det.parameters(), lr=3e-3)
    history = []
    for step in range(25):
        dn = det.denoising_queries(labels, gts, generator=torch.Generator().manual_seed(step))
        out = det(levels, (H, W), k, c2e, a, denoising=dn)
        terms = detection_loss(out, labels, gts)
        loss = terms["det_dn_cls"] + terms["det_dn_box"]
        opt.zero_grad()
        loss.backward()
        if step == 0:
            assert det.layers[0].refine[-1].weight.grad.abs().sum() > 0
        opt.step()
        history.append(float(loss.detach()))
    assert sum(history[-5:]) < 0.6 * sum(history[:5]), history


def test_loss_of_a_padded_batch_by_hand():
    """Two samples (2 and 1 boxes), one group with negatives: 4 queries each, sample 1's slot 1 and 3 are
    padding. The loss counts the 6 valid queries (focal on their logits, L1 on the 3 assigned ones) over 6."""
    torch.manual_seed(0)
    labels, boxes = [torch.tensor([0, 1]), torch.tensor([1])], [_boxes((5, 0), (15, 5)), _boxes((3, 3))]
    dn = make_denoising_queries(labels, boxes, groups=1, generator=torch.Generator().manual_seed(2))
    assert dn.valid.tolist() == [[True, True, True, True], [True, False, True, False]]
    logits = torch.randn(2, 4, 2)
    enc = torch.randn(2, 4, 10)
    got = denoising_loss(
        dn, [logits], [enc], _focal, cls_weight=2.0, box_weight=0.25, reg_weights=[2.0] * 3 + [1.0] * 7
    )
    cls_sum, box_sum = torch.zeros(()), torch.zeros(())
    reg = torch.tensor([2.0] * 3 + [1.0] * 7)
    for i in range(2):
        for q in range(4):
            if not dn.valid[i, q]:
                continue
            target = torch.zeros(2)
            c = int(dn.cls_target[i, q])
            if c >= 0:
                target[c] = 1.0
                box_sum = box_sum + ((enc[i, q] - dn.box_target[i, q]).abs() * reg).sum()
            cls_sum = cls_sum + _focal(logits[i, q], target)
    assert int((dn.cls_target >= 0).sum()) == 3
    torch.testing.assert_close(got["det_dn_cls"], 2.0 * cls_sum / 6)
    torch.testing.assert_close(got["det_dn_box"], 0.25 * box_sum / 6)


def _focal(logits, targets):
    return sigmoid_focal_loss(logits, targets, 0.25, 2.0)


def test_negative_labels_are_refused():
    with pytest.raises(ValueError, match="class ids >= 0"):
        make_denoising_queries([torch.tensor([0, -1])], [_boxes((1, 1), (2, 2))], groups=1)


def test_bad_noise_scale_is_one_line():
    with pytest.raises(ValueError, match="dn_noise_scale needs 10 values"):
        SparseDetector(num_classes=2, dn_noise_scale=[1.0, 2.0])


def test_the_full_model_trains_with_denoising_and_evaluates_without():
    from test_duocc_model import SMALL, _batch, _loss

    torch.manual_seed(0)
    cfg = runner.load_config(
        ["duocc/full", "occplug/trainer/debug"], [*SMALL, "model.scene.query_agg.detector.num_dn_groups=2"]
    )
    dm, model = runner.build_run(cfg)
    assert model.scene.query_agg.detector.num_dn_groups == 2
    batch = _batch(dm, [0, 3])
    model.train()
    loss, terms = _loss(model, batch)
    assert {"detection/det_dn_cls", "detection/det_dn_box"} <= set(terms)
    assert torch.isfinite(loss)
    loss.backward()
    model.eval()
    with torch.no_grad():
        _, terms = _loss(model, batch)
    assert not any("det_dn" in k for k in terms)
