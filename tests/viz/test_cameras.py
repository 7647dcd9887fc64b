"""Occupancy ray cast through the data set's own cameras, overlays, LiDAR, rig layout."""

import numpy as np
import pytest
import torch
from viz_helpers import CAR, FREE, TRUCK

from occplug.geometry import project_to_image
from occplug.viz.cameras import blend_overlay, downscale_matrix, lidar_in_cameras, occupancy_in_cameras, rig_layout

# Tiny world: grid (-16, -16, -1) .. (16, 16, 5.4) at 0.8 m; cameras as in the nuScenes-like rig.
FRONT_BLOCK = (slice(30, 33), slice(19, 22), slice(2, 5))  # x [8, 10.4), y [-0.8, 1.6), z [0.6, 3.0)
BACK_BLOCK = (slice(8, 11), slice(18, 21), slice(2, 5))  # x [-9.6, -7.2), y [-1.6, 0.8)


def _labels(grid):
    labels = torch.full(grid.shape, FREE, dtype=torch.uint8)
    labels[FRONT_BLOCK] = CAR
    labels[BACK_BLOCK] = TRUCK
    return labels


def _centre(grid, block):
    lo = torch.tensor([s.start for s in block])
    hi = torch.tensor([s.stop for s in block])
    return (grid.index_to_coord(lo) + grid.index_to_coord(hi - 1)).double()[None] / 2


def _pixel(frame, cam, point, aug=None):
    aug = frame.img_aug[cam] if aug is None else aug
    uv, depth = project_to_image(point, frame.intrinsics[cam].double(), frame.cam_to_ego[cam].double(), aug.double())
    assert depth.item() > 0
    u, v = uv[0].round().long().tolist()
    return v, u


def test_block_centre_pixel_shows_the_block_class_in_each_camera(tiny_dm, tiny_frame, palette):
    grid, frame = tiny_dm.grid, tiny_frame
    names = list(frame.camera_names)
    front, back = names.index("CAM_FRONT"), names.index("CAM_BACK")
    classes = occupancy_in_cameras(
        _labels(grid), grid, palette, frame.intrinsics, frame.cam_to_ego, frame.image_size, frame.img_aug, max_rays=None
    )
    assert classes.shape == (frame.num_cameras, *frame.image_size)
    v, u = _pixel(frame, front, _centre(grid, FRONT_BLOCK))
    assert classes[front, v, u] == CAR
    v, u = _pixel(frame, back, _centre(grid, BACK_BLOCK))
    assert classes[back, v, u] == TRUCK
    assert (classes[front] == CAR).sum() > 4 and (classes[front] == TRUCK).sum() == 0
    assert classes[front, 0, 0] == -1  # free space (sky above the empty grid)
    assert set(classes.unique().tolist()) == {-1, CAR, TRUCK}


def test_overlay_blends_the_class_colour_and_leaves_free_pixels_alone(tiny_dm, tiny_frame, palette):
    grid, frame = tiny_dm.grid, tiny_frame
    front = list(frame.camera_names).index("CAM_FRONT")
    classes = occupancy_in_cameras(
        _labels(grid), grid, palette, frame.intrinsics, frame.cam_to_ego, frame.image_size, frame.img_aug
    )
    image = frame.images[front]
    rgb = blend_overlay(image, classes[front], palette, alpha=0.4)
    v, u = _pixel(frame, front, _centre(grid, FRONT_BLOCK))
    expected = np.round(0.4 * palette.colors[CAR] + 0.6 * image[:, v, u].numpy() * 255)
    assert np.abs(rgb[v, u].astype(float) - expected).max() <= 1
    plain = np.round(image.permute(1, 2, 0).numpy() * 255)
    free = classes[front].numpy() < 0
    assert np.abs(rgb[free].astype(float) - plain[free]).max() <= 1


def test_projection_stays_exact_under_image_augmentation(tiny_dm, tiny_frame, palette):
    grid, frame = tiny_dm.grid, tiny_frame
    front = list(frame.camera_names).index("CAM_FRONT")
    aug = torch.tensor([[0.5, 0.0, -3.0], [0.0, 0.5, -1.0], [0.0, 0.0, 1.0]])  # resize by 1/2, then crop
    h, w = 14, 26
    classes = occupancy_in_cameras(
        _labels(grid),
        grid,
        palette,
        frame.intrinsics[front : front + 1],
        frame.cam_to_ego[front : front + 1],
        (h, w),
        aug[None],
    )
    v, u = _pixel(frame, front, _centre(grid, FRONT_BLOCK), aug=aug)
    assert 0 <= v < h and 0 <= u < w
    assert classes[0, v, u] == CAR


def test_strided_casting_repeats_block_results(tiny_dm, tiny_frame, palette):
    grid, frame = tiny_dm.grid, tiny_frame
    labels = _labels(grid)
    full = occupancy_in_cameras(
        labels, grid, palette, frame.intrinsics, frame.cam_to_ego, frame.image_size, frame.img_aug, max_rays=None
    )
    strided = occupancy_in_cameras(
        labels,
        grid,
        palette,
        frame.intrinsics,
        frame.cam_to_ego,
        frame.image_size,
        frame.img_aug,
        max_rays=full.numel() // 4,
    )  # stride 2
    assert strided.shape == full.shape
    assert torch.equal(strided[:, ::2, ::2], strided[:, 1::2, 1::2])  # 2 x 2 blocks share one ray
    assert (strided == full).float().mean() > 0.95
    # one small-image pixel covers f x f pixels centred where the downscaled pixel centre maps
    d = downscale_matrix(2)
    assert torch.allclose(d @ torch.tensor([0.5, 0.5, 1.0]), torch.tensor([0.0, 0.0, 1.0]))


def test_lidar_point_lands_on_its_pixel_with_its_range(tiny_frame):
    frame = tiny_frame
    front = list(frame.camera_names).index("CAM_FRONT")
    target_ego = torch.tensor([[9.2, 0.4, 1.8]], dtype=torch.float64)
    lidar_xyz = target_ego - frame.lidar_to_ego[:3, 3].double()  # the LiDAR frame is axis-aligned with the ego's
    points = torch.cat([lidar_xyz, torch.tensor([[0.5]], dtype=torch.float64)], -1).float()
    views = lidar_in_cameras(
        points, frame.lidar_to_ego, frame.intrinsics, frame.cam_to_ego, frame.image_size, frame.img_aug
    )
    assert len(views) == frame.num_cameras
    assert len(views[front].range) == 1
    assert sum(len(v.range) for v in views) == 1  # no other camera sees a point straight ahead
    uv, _ = project_to_image(target_ego, frame.intrinsics[front].double(), frame.cam_to_ego[front].double())
    assert np.allclose(views[front].uv[0], uv[0].numpy(), atol=1e-3)
    assert views[front].range[0] == pytest.approx(float(lidar_xyz.norm()), rel=1e-5)


def test_lidar_views_are_sorted_far_to_near(tiny_frame):
    views = lidar_in_cameras(
        tiny_frame.points,
        tiny_frame.lidar_to_ego,
        tiny_frame.intrinsics,
        tiny_frame.cam_to_ego,
        tiny_frame.image_size,
        tiny_frame.img_aug,
    )
    assert sum(len(v.range) for v in views) > 100
    for view in views:
        assert np.all(np.diff(view.depth) <= 1e-6)


def test_rig_layout_places_cameras_by_name():
    nus = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")
    assert rig_layout(nus) == [(0, 1), (0, 2), (0, 0), (1, 1), (1, 0), (1, 2)]
    assert rig_layout(["front", "cam_back"]) == [(0, 1), (1, 1)]
    assert rig_layout(["image_2"]) == [(0, 0)]  # unknown names fill slots in reading order
    assert rig_layout(["a", "CAM_FRONT", "b", "c"]) == [(0, 0), (0, 1), (0, 2), (1, 0)]
