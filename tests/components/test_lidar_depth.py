"""``lidar_depth``: BEVDepth's depth targets from projected LiDAR points, and its loss."""

import torch
import torch.nn.functional as F

from occplug.components.depth_supervision import (
    LidarDepthSupervision,
    lidar_depth_targets,
)
from occplug.interfaces import Lifted, ModelOutputs
from occplug.plugins import get_registry
from occplug.testing import hand_batch as build_batch
from occplug.testing.fixtures import make_tiny_batch

# One camera looking along ego +x: camera x = -ego y, camera y = -ego z, camera z = ego x.
CAM_TO_EGO = torch.tensor([[0.0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
K = torch.tensor([[10.0, 0, 8], [0, 10, 4], [0, 0, 1]])
CENTERS = torch.arange(9, dtype=torch.float32) + 1.5  # depth_bins [1, 10, 1]


def hand_batch(points, img_aug=None):
    """B = 1, one 8 x 16 camera, LiDAR frame = ego frame."""
    return build_batch(
        1,
        image_hw=(8, 16),
        intrinsics=K.view(1, 1, 3, 3),
        cam_to_ego=CAM_TO_EGO.view(1, 1, 4, 4),
        img_aug=(torch.eye(3) if img_aug is None else img_aug).view(1, 1, 3, 3),
        lidar_to_ego=torch.eye(4).view(1, 4, 4),
        points=[torch.tensor(points, dtype=torch.float32)],
    )


POINTS = [
    [5.7, 0.0, 0.0, 1.0],  # u = 8, v = 4: pixel [4, 8], cell (1, 2); depth 5.7 -> bin 4 (centre 5.5)
    [9.1, 0.0, 0.0, 1.0],  # same cell, farther: the nearest return wins
    [-3.0, 0.0, 0.0, 1.0],  # behind the camera
    [12.0, 6.0, 0.0, 1.0],  # u = 3: cell (1, 0), but 12 m lies beyond the last bin
    [4.2, -2.52, 1.05, 1.0],  # u = 14, v = 1.5 -> pixel [2, 14], cell (0, 3); depth 4.2 -> bin 3
    [2.0, -5.0, 0.0, 1.0],  # u = 33: outside the image
]


def test_targets_of_hand_placed_points():
    target = lidar_depth_targets(hand_batch(POINTS), (2, 4), 4, CENTERS)
    expected = torch.full((1, 1, 2, 4), -1)
    expected[0, 0, 1, 2] = 4
    expected[0, 0, 0, 3] = 3
    assert torch.equal(target, expected)


def test_targets_follow_the_image_augmentation():
    flip = torch.tensor([[-1.0, 0, 15], [0, 1, 0], [0, 0, 1]])  # horizontal flip of the 16-pixel-wide image
    target = lidar_depth_targets(hand_batch(POINTS, img_aug=flip), (2, 4), 4, CENTERS)
    expected = torch.full((1, 1, 2, 4), -1)
    expected[0, 0, 1, 1] = 4  # u 8 -> 7: column 7, cell 1
    expected[0, 0, 0, 0] = 3  # u 14 -> 1: cell 0
    assert torch.equal(target, expected)


def test_loss_is_bevdepths_binary_cross_entropy():
    batch = hand_batch(POINTS)
    logits = torch.randn(1, 1, 9, 2, 4)
    probs = logits.softmax(dim=2)
    lifted = Lifted(volume=torch.zeros(1, 1, 1, 1, 1), grid=None, depth_probs=probs, depth_bins=CENTERS, image_stride=4)
    outputs = ModelOutputs(image_features=torch.zeros(1), lifted=lifted, scene=None, heads={}, query=None)
    loss = LidarDepthSupervision()(batch, outputs)["depth"]
    p1, p2 = probs[0, 0, :, 1, 2], probs[0, 0, :, 0, 3]
    manual = (
        F.binary_cross_entropy(p1, F.one_hot(torch.tensor(4), 9).float(), reduction="sum")
        + F.binary_cross_entropy(p2, F.one_hot(torch.tensor(3), 9).float(), reduction="sum")
    ) / 2
    assert torch.allclose(loss, manual)
    assert LidarDepthSupervision.requires == frozenset({"points"})


def test_targets_agree_with_the_synthetic_cameras_depth_maps():
    batch = make_tiny_batch()
    stride, centers = 8, torch.arange(39, dtype=torch.float32) + 1.5
    big_h, big_w = batch.images.shape[-2:]
    h, w = big_h // stride, big_w // stride
    target = lidar_depth_targets(batch, (h, w), stride, centers)
    has = target >= 0
    assert has.sum() > 100
    cells = batch.depth[..., : h * stride, : w * stride].unflatten(-1, (w, stride)).unflatten(-3, (h, stride))
    near = torch.where(cells > 0, cells, torch.full_like(cells, float("inf"))).amin(dim=(-3, -1))
    far = cells.amax(dim=(-3, -1))
    depth = centers[target[has]]
    inside = (depth >= near[has] - 0.5) & (depth <= far[has] + 0.5)  # half a bin of quantisation
    assert inside.float().mean() > 0.95


def test_training_on_lidar_depth_lowers_the_loss():
    torch.manual_seed(0)
    batch = make_tiny_batch()
    encoder = get_registry().build("encoder", {"type": "small_cnn", "out_channels": 16, "stride": 8})
    grid = {"range": [-24.0, -24.0, -1.0, 24.0, 24.0, 5.4], "voxel_size": 0.8}
    lss = get_registry().build(
        "view_transform",
        {"type": "lss", "grid": grid, "out_channels": 8, "depth_bins": [1.0, 40.0, 1.0]},
        in_channels=16,
        image_stride=8,
    )
    source = get_registry().build("supervision", {"type": "lidar_depth"})
    params = [*encoder.parameters(), *lss.parameters()]
    opt = torch.optim.Adam(params, lr=3e-3)
    losses = []
    for _ in range(15):
        lifted = lss(encoder(batch.images), batch)
        outputs = ModelOutputs(image_features=torch.zeros(1), lifted=lifted, scene=None, heads={}, query=None)
        loss = source(batch, outputs)["depth"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.7 * losses[0], losses
