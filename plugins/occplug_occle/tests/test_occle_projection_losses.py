"""OccLE's projection (§3.4 Eq. 5, Appendix C.1), semantic-branch UNets (§3.2) and losses (§3.5) against their
definitions."""

import math

import pytest
import torch
import torch.nn.functional as F

from occplug.geometry import GridSpec, make_pose, project_to_image
from occplug.nn import UNet2d, UNet3d
from occplug.ops import feature_cell_centers
from occplug_occle.blocks.losses import (
    OccupancyLoss,
    class_weights_from_frequencies,
    geo_scal_loss,
    lidar_count_mask,
    sem_scal_loss,
    weighted_cross_entropy,
)
from occplug_occle.blocks.projection import ProjectionHead, ScatterProjection, feature_map_intrinsics, scatter_project

# ------------------------------------------------------------------ a pinhole camera looking along ego +x
H, W = 24, 32
GRID = GridSpec(range=(-4.0, -4.0, -2.0, 12.0, 4.0, 2.0), voxel_size=0.5)  # (32, 16, 8), centres at 0.25 + 0.5 k
CAM_POS = (0.25, 0.25, 0.25)  # a voxel centre: lattice steps from it reach other voxel centres


def camera(batch: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """``(B, 3, 3)`` intrinsics and ``(B, 4, 4)`` cam_to_ego of an OpenCV camera (x right, y down, z forward)
    at ``CAM_POS`` looking along ego +x (ego: x forward, y left, z up)."""
    # columns: the camera's x, y, z axes in the ego frame: right = -y_ego, down = -z_ego, forward = +x_ego
    rot = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    pose = make_pose(rot, torch.tensor(CAM_POS))
    # integer principal point and a focal length that puts the lattice directions used below on pixel centres
    k = torch.tensor([[20.0, 0.0, 16.0], [0.0, 20.0, 12.0], [0.0, 0.0, 1.0]])
    return k.expand(batch, 3, 3).clone(), pose.expand(batch, 4, 4).clone()


def voxel_at(offset: tuple[float, float, float]) -> tuple[int, int, int]:
    """Index of the voxel whose centre is ``CAM_POS + offset`` (offset in multiples of 0.5 m)."""
    point = torch.tensor([[c + o for c, o in zip(CAM_POS, offset, strict=True)]])
    idx = GRID.coord_to_index(point)[0]
    assert torch.allclose(GRID.index_to_coord(idx), point[0])
    return tuple(int(i) for i in idx)


def one_hot_volume(*voxels: tuple[int, int, int], channels: int = 2) -> torch.Tensor:
    vol = torch.zeros(1, channels, *GRID.shape)
    for v in voxels:
        vol[(0, 0, *v)] = 1.0
    return vol


def test_camera_convention_points_ego_forward_to_the_principal_point():
    k, pose = camera()
    uv, depth = project_to_image(torch.tensor([[[5.25, 0.25, 0.25], [5.25, 1.25, 1.25]]]), k, pose)
    assert torch.allclose(uv[0, 0], torch.tensor([16.0, 12.0])) and float(depth[0, 0]) == pytest.approx(5.0)
    # left (+y) and up (+z) in the ego frame are smaller u and v in the image
    assert float(uv[0, 1, 0]) < 16.0 and float(uv[0, 1, 1]) < 12.0


def test_single_voxel_lands_on_the_pixel_of_the_core_projection_with_value_one():
    k, pose = camera()
    idx = voxel_at((3.5, 1.0, -1.5))  # lands at u = 10.29, v = 20.57: away from pixel borders
    uv, depth = project_to_image(GRID.index_to_coord(torch.tensor([idx])).unsqueeze(0), k, pose)
    assert float(depth) > 0
    col, row = (int(math.floor(float(c) + 0.5)) for c in uv[0, 0])
    assert 0 <= col < W and 0 <= row < H

    out = scatter_project(one_hot_volume(idx), GRID, k, pose, (H, W))
    assert out.shape == (1, 2, H, W)
    assert float(out[0, 0, row, col]) == 1.0
    assert float(out.abs().sum()) == 1.0  # nothing anywhere else, nothing in channel 1


def test_two_voxels_on_one_ray_sum():
    k, pose = camera()
    near, far = voxel_at((2.0, 0.5, 0.5)), voxel_at((4.0, 1.0, 1.0))  # same direction from the camera
    out = scatter_project(one_hot_volume(near, far), GRID, k, pose, (H, W))
    # direction (2, 0.5, 0.5) ego -> camera (x, y, z) = (-0.5, -0.5, 2): u = 16 - 20/4 = 11, v = 12 - 20/4 = 7
    assert float(out[0, 0, 7, 11]) == 2.0
    assert float(out.sum()) == 2.0


def test_voxels_behind_the_camera_or_outside_the_image_contribute_nothing():
    k, pose = camera()
    behind = voxel_at((-2.0, 0.5, 0.5))  # would land on u = 21, v = 17 (inside the image) without the depth test
    beside = voxel_at((0.5, 3.5, 0.0))  # in front, but u = 16 - 20 * 7 far outside
    inside = voxel_at((0.0, 0.0, 0.0))  # the voxel holding the camera: depth 0
    for vox in (behind, beside, inside):
        assert float(scatter_project(one_hot_volume(vox), GRID, k, pose, (H, W)).abs().sum()) == 0.0


def test_distance_mode_weights_a_near_voxel_more_than_a_far_one():
    k, pose = camera()
    near, far = voxel_at((2.0, 0.5, 0.5)), voxel_at((4.0, 1.0, 1.0))  # the far one is exactly twice as far
    vol = torch.zeros(1, 2, *GRID.shape)
    vol[(0, 0, *near)] = 1.0  # channel 0 reads the near voxel's weight, channel 1 the far one's
    vol[(0, 1, *far)] = 1.0
    out = scatter_project(vol, GRID, k, pose, (H, W), mode="distance")
    # w_p = n * (1/d_p) / sum_q (1/d_q) over every voxel q projecting into the pixel: w_near / w_far = d_far / d_near
    assert float(out[0, 0, 7, 11]) / float(out[0, 1, 7, 11]) == pytest.approx(2.0, rel=1e-5)
    assert float(out[0, 0, 7, 11]) > 1.0  # above the sum mode's weight
    # the near voxel's weight from the definition, over the voxel centres the core projects into pixel (7, 11)
    centres = GRID.centers().reshape(1, -1, 3)
    uv, depth = project_to_image(centres, k, pose)
    in_pixel = (depth[0] > 0) & (torch.floor(uv[0] + 0.5) == torch.tensor([11.0, 7.0])).all(-1)
    inv = [1.0 / float(d) for d in (centres[0, in_pixel] - torch.tensor(CAM_POS)).norm(dim=-1)]
    d_near = math.dist(CAM_POS, GRID.index_to_coord(torch.tensor(near)).tolist())
    assert float(out[0, 0, 7, 11]) == pytest.approx(len(inv) * (1.0 / d_near) / sum(inv), rel=1e-5)
    # the weights of a pixel average to 1: an all-ones volume projects to the voxel count, as in the sum mode
    ones = torch.ones(1, 1, *GRID.shape)
    count = scatter_project(ones, GRID, k, pose, (H, W))
    assert float(count[0, 0, 7, 11]) > 2  # more voxel centres than the two above fall in that pixel
    assert torch.allclose(scatter_project(ones, GRID, k, pose, (H, W), mode="distance"), count, rtol=1e-5)


def test_projection_batches_cameras_and_is_differentiable():
    k, pose = camera(batch=2)
    torch.manual_seed(0)
    vol = torch.randn(2, 3, *GRID.shape, requires_grad=True)
    proj = ScatterProjection(GRID, mode="sum")
    multi = proj(vol, k.unsqueeze(1).expand(2, 2, 3, 3), pose.unsqueeze(1).expand(2, 2, 4, 4), (H, W))
    single = proj(vol, k, pose, (H, W))
    assert multi.shape == (2, 2, 3, H, W) and single.shape == (2, 3, H, W)
    assert torch.allclose(multi[:, 0], single, atol=1e-5) and torch.allclose(multi[:, 1], single, atol=1e-5)
    assert torch.allclose(single[1], scatter_project(vol[1:], GRID, k[1:], pose[1:], (H, W))[0], atol=1e-5)
    single.sum().backward()
    near = voxel_at((2.0, 0.5, 0.5))
    assert float(vol.grad[(0, 1, *near)]) == 1.0  # d(sum of the image)/d(visible voxel) = 1
    assert float(vol.grad[(0, 1, *voxel_at((-2.0, 0.5, 0.5)))]) == 0.0  # behind the camera
    logits = ProjectionHead(3, 5, hidden_channels=8)(single)
    assert logits.shape == (2, 5, H, W)


def test_feature_map_intrinsics_follow_the_core_feature_cell_centres():
    k, pose = camera()
    stride = 4
    k_feat = feature_map_intrinsics(k, stride)
    pts = torch.tensor([[[5.25, 0.75, -1.25], [3.0, -2.0, 0.5]]])
    uv_img, _ = project_to_image(pts, k, pose)
    uv_feat, _ = project_to_image(pts, k_feat, pose)
    # a feature coordinate (c, r) sits at image pixel s * (c, r) + (s - 1) / 2, as feature_cell_centers places cells
    assert torch.allclose(uv_feat * stride + (stride - 1) / 2, uv_img, atol=1e-4)
    centres = feature_cell_centers(2, 3, stride)
    assert torch.allclose(centres[1, 2], torch.tensor([2.0, 1.0]) * stride + (stride - 1) / 2)


# ------------------------------------------------------------------ losses
def _logits_from_probs(probs: list[list[float]]) -> torch.Tensor:
    """``(1, K, M)`` logits whose softmax over K is ``probs`` (``M`` cells of ``K`` probabilities each)."""
    return torch.tensor(probs, dtype=torch.float64).log().T.unsqueeze(0)


def _bce1(x: float) -> float:
    return -max(math.log(x), -100.0) if x > 0 else 100.0


def _scal_terms(p: list[float], y: list[int]) -> float:
    """BCE(precision) + BCE(recall) + BCE(specificity), each against 1, by plain arithmetic (MonoScene)."""
    hit = sum(pi * yi for pi, yi in zip(p, y, strict=True))
    total = _bce1(hit / sum(p)) + _bce1(hit / sum(y))
    if sum(1 - yi for yi in y) > 0:
        total += _bce1(sum((1 - pi) * (1 - yi) for pi, yi in zip(p, y, strict=True)) / sum(1 - yi for yi in y))
    return total


def test_scal_losses_match_a_hand_computation_two_classes():
    # 4 voxels, P(class 1) = 0.9, 0.2, 0.6, 0.3; labels 1, 0, 1, 0; class 0 = free
    logits = _logits_from_probs([[0.1, 0.9], [0.8, 0.2], [0.4, 0.6], [0.7, 0.3]])
    labels = torch.tensor([[1, 0, 1, 0]])
    # class 1: hit = 0.9 + 0.6 = 1.5, sum p = 2.0, sum y = 2, true negatives = 0.8 + 0.7 = 1.5 of 2 -> all 0.75;
    # class 0 is the mirror image (hit = 0.8 + 0.7, sum p = 2.0, ...): also 0.75 three times. geo_scal's
    # occupied/free split is exactly class 1 vs class 0. So both losses are 3 * -log(0.75).
    expected = 3 * -math.log(0.75)
    assert float(sem_scal_loss(logits, labels)) == pytest.approx(expected, rel=1e-9)
    assert float(geo_scal_loss(logits, labels, free_label=0)) == pytest.approx(expected, rel=1e-9)


def test_scal_losses_match_a_hand_computation_three_classes_with_ignore_and_mask():
    probs = [[0.7, 0.2, 0.1], [0.1, 0.6, 0.3], [0.2, 0.3, 0.5], [0.5, 0.1, 0.4], [0.3, 0.3, 0.4], [0.1, 0.1, 0.8]]
    labels = [0, 1, 2, 2, 255, 1]  # the fifth voxel is unknown
    mask = [True, True, True, True, True, False]  # the sixth is masked out
    kept = [i for i in range(6) if labels[i] != 255 and mask[i]]
    p = [probs[i] for i in kept]
    y = [labels[i] for i in kept]

    sem = [_scal_terms([pi[c] for pi in p], [int(yi == c) for yi in y]) for c in range(3) if c in y]
    expected_sem = sum(sem) / len(sem)
    occupied = [1 - pi[0] for pi in p]  # free class 0
    expected_geo = _scal_terms(occupied, [int(yi != 0) for yi in y])

    logits = _logits_from_probs(probs)
    lab = torch.tensor([labels])
    m = torch.tensor([mask])
    assert float(sem_scal_loss(logits, lab, mask=m)) == pytest.approx(expected_sem, rel=1e-9)
    assert float(geo_scal_loss(logits, lab, mask=m, free_label=0)) == pytest.approx(expected_geo, rel=1e-9)
    # free_label picks the "empty" channel: with class 2 as free the split changes
    expected_geo2 = _scal_terms([1 - pi[2] for pi in p], [int(yi != 2) for yi in y])
    assert float(geo_scal_loss(logits, lab, mask=m, free_label=2)) == pytest.approx(expected_geo2, rel=1e-9)


def test_class_weighted_ce_equals_torch_cross_entropy_with_the_weights():
    torch.manual_seed(0)
    freqs = [5.4e9, 1.6e7, 7.3e4, 2.0e5]
    w = class_weights_from_frequencies(freqs)
    assert w.tolist() == pytest.approx([1 / math.log(f + 0.001) for f in freqs], rel=1e-6)
    assert w[2] > w[3] > w[1] > w[0]  # rarer classes weigh more
    with pytest.raises(ValueError, match="raw class counts"):
        class_weights_from_frequencies([0.7, 0.3])  # normalised frequencies would give negative weights

    logits = torch.randn(2, 4, 5, 6, 3)
    labels = torch.randint(0, 4, (2, 5, 6, 3))
    labels[0, 0, 0] = 255
    ref = F.cross_entropy(logits, labels, weight=w, ignore_index=255)
    assert float(weighted_cross_entropy(logits, labels, w)) == pytest.approx(float(ref), rel=1e-6)
    mask = torch.rand(2, 5, 6, 3) > 0.5
    sel = mask & (labels != 255)
    ref_masked = F.cross_entropy(logits.movedim(1, -1)[sel], labels[sel], weight=w)
    assert float(weighted_cross_entropy(logits, labels, w, mask=mask)) == pytest.approx(float(ref_masked), rel=1e-6)


def test_occupancy_loss_is_minimal_for_perfect_predictions_and_larger_for_worse():
    torch.manual_seed(0)
    labels = torch.randint(0, 4, (2, 6, 6, 4))
    loss = OccupancyLoss(class_weights=[0.5, 1.0, 2.0, 1.5], free_label=0)
    perfect = F.one_hot(labels, 4).movedim(-1, 1).float() * 30.0
    near_miss = perfect * 0.1  # right argmax, low confidence
    random = torch.randn(2, 4, 6, 6, 4)
    totals = [sum(loss(x, labels).values()) for x in (perfect, near_miss, random)]
    assert float(totals[0]) < 1e-6
    assert float(totals[0]) < float(totals[1]) < float(totals[2])
    terms = loss(random, labels)
    assert set(terms) == {"ce", "sem_scal", "geo_scal"} and all(float(v) > 0 for v in terms.values())


def test_masked_voxels_do_not_affect_any_loss():
    torch.manual_seed(1)
    logits = torch.randn(1, 3, 4, 4, 2)
    labels = torch.randint(0, 3, (1, 4, 4, 2))
    mask = torch.rand(1, 4, 4, 2) > 0.4
    changed = logits.clone()
    changed[:, :, ~mask[0]] = torch.randn(3, int((~mask).sum()))  # new predictions only where masked out
    changed_labels = labels.clone()
    changed_labels[~mask] = (labels[~mask] + 1) % 3
    loss = OccupancyLoss(class_weights=[1.0, 2.0, 3.0])
    before = loss(logits, labels, mask)
    after = loss(changed, changed_labels, mask)
    for name in before:
        assert float(after[name]) == pytest.approx(float(before[name]), rel=1e-6)
    unmasked = loss(changed, labels)
    assert float(unmasked["ce"]) != pytest.approx(float(before["ce"]), rel=1e-6)
    # nothing counted: exact zeros that still backpropagate
    empty = loss(logits.requires_grad_(), labels, torch.zeros_like(mask))
    total = sum(empty.values())
    total.backward()
    assert float(total.detach()) == 0.0 and logits.grad is not None


def test_lidar_count_mask_keeps_voxels_with_more_than_one_point():
    grid = GridSpec(range=(0.0, 0.0, 0.0, 2.0, 2.0, 1.0), voxel_size=0.5)  # (4, 4, 2)
    pts = torch.tensor([[0.1, 0.1, 0.1], [0.2, 0.3, 0.4], [1.6, 0.6, 0.7], [5.0, 0.1, 0.1]])  # 2, 1, outside
    mask = lidar_count_mask([pts, pts[:1]], grid)
    assert mask.shape == (2, 4, 4, 2)
    assert mask[0].nonzero().tolist() == [[0, 0, 0]]
    assert not bool(mask[1].any())
    assert int(lidar_count_mask([pts], grid, min_points=1).sum()) == 2


# ------------------------------------------------------------------ the core's UNets (occplug.nn) under OccLE's losses
def _fit(net: torch.nn.Module, x: torch.Tensor, loss_fn, steps: int = 20) -> tuple[float, float]:
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    losses = []
    for _ in range(steps):
        opt.zero_grad()
        loss = loss_fn(net(x))
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    return losses[0], losses[-1]


def test_unets_fit_a_toy_segmentation_target():
    torch.manual_seed(0)
    # 2D: the class of a pixel is which of 3 colour channels is brightest
    img = torch.rand(2, 3, 24, 32)
    target = img.argmax(1)
    first, last = _fit(UNet2d(3, 3, base_channels=8, depth=2), img, lambda y: weighted_cross_entropy(y, target))
    assert last < 0.5 * first

    # 3D, with the full occupancy loss: voxels with a positive first feature are occupied (class 1 or 2 by the
    # sign of the second), the rest free (class 0)
    feats = torch.randn(1, 4, 16, 16, 4)
    labels = torch.where(feats[:, 0] > 0, 1 + (feats[:, 1] > 0).long(), torch.zeros_like(feats[:, 0]).long())
    occ = OccupancyLoss(free_label=0)
    first, last = _fit(UNet3d(4, 3, base_channels=4, depth=2), feats, lambda y: sum(occ(y, labels).values()))
    assert last < 0.7 * first
