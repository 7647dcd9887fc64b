"""BEV class maps and error maps on hand-built grids."""

import numpy as np
import pytest
import torch
from viz_helpers import BUILDING, CAR, FREE, ROAD, TRUCK, empty

from occplug.viz import bev as B
from occplug.viz.style import BACKGROUND, ERROR_COLORS


def test_block_shows_its_colour_at_the_expected_pixel_and_free_space_is_background(grid, palette):
    labels = empty(grid)
    labels[12:14, 3:5, 1:3] = CAR  # x in [1, 2), y in [-2.5, -1.5), z in [-0.5, 0.5)
    image = B.bev_rgb(labels, palette)
    assert image.shape == (grid.shape[0], grid.shape[1], 3) and image.dtype == np.uint8
    row, col = B.bev_pixel(grid, torch.tensor([1.5, -2.0])).tolist()  # the block's centre
    assert (row, col) == (grid.shape[0] - 1 - 13, grid.shape[1] - 1 - 4)  # forward up, left left
    assert tuple(image[row, col]) == tuple(palette.colors[CAR])
    car = np.all(image == palette.colors[CAR], axis=-1)
    assert car.sum() == 4  # 2 x 2 columns, nothing else
    assert np.all(image[~car] == np.asarray(BACKGROUND))


def test_top_down_takes_the_highest_non_free_voxel(grid, palette):
    labels = empty(grid)
    labels[3, 4, 0] = ROAD
    labels[3, 4, 5] = TRUCK
    labels[5, 5, 0] = ROAD
    labels[5, 5, 6] = 255  # ignored: not occupied
    classes, height = B.top_down(labels, palette)
    assert classes[3, 4] == TRUCK and height[3, 4] == 5
    assert classes[5, 5] == ROAD and height[5, 5] == 0
    assert classes[0, 0] == -1 and height[0, 0] == -1
    assert (classes >= 0).sum() == 2


def test_ego_forward_is_up_and_left_is_left(grid, palette):
    labels = empty(grid)
    labels[-1, :, 0] = ROAD  # the front edge (largest x)
    labels[:, -1, 0] = BUILDING  # the left edge (largest y)
    image = B.bev_rgb(labels, palette)
    assert np.all(image[0, 1:] == palette.colors[ROAD])  # top row
    assert np.all(image[1:, 0] == palette.colors[BUILDING])  # left column


def test_image_extent_puts_points_on_their_pixels(grid):
    left, right, bottom, top = B.image_extent(grid)
    pts = torch.tensor([[1.3, -2.2], [-4.9, 3.9], [4.9, -3.9], [0.1, 0.1]])  # off voxel boundaries
    rows = np.floor((top - pts[:, 0].numpy()) / (top - bottom) * grid.shape[0]).astype(int)
    cols = np.floor((left - pts[:, 1].numpy()) / (left - right) * grid.shape[1]).astype(int)
    assert np.array_equal(np.stack([rows, cols], -1), B.bev_pixel(grid, pts).numpy())


def test_error_map_labels_each_of_its_four_cases(grid, palette):
    gt, pred = empty(grid), empty(grid)
    gt[1, 1, 2] = pred[1, 1, 2] = CAR  # correct
    gt[2, 2, 2], pred[2, 2, 2] = CAR, TRUCK  # wrong class
    gt[3, 3, 2] = CAR  # missed
    pred[4, 4, 2] = CAR  # false occupied
    gt[5, 5, 0] = pred[5, 5, 0] = ROAD  # correct ground under ...
    pred[5, 5, 4] = TRUCK  # ... a false voxel above it: seen from above, false occupied
    gt[6, 6, 3] = 255  # an ignored truth is not judged
    pred[6, 6, 3] = CAR
    codes = B.error_codes(gt, pred, palette)
    assert codes[1, 1] == B.CORRECT
    assert codes[2, 2] == B.WRONG_CLASS
    assert codes[3, 3] == B.MISSED
    assert codes[4, 4] == B.FALSE_OCCUPIED
    assert codes[5, 5] == B.FALSE_OCCUPIED
    assert codes[6, 6] == B.EMPTY
    assert (codes != B.EMPTY).sum() == 5
    rgb = B.error_rgb(codes)
    for (i, j), code in {(1, 1): B.CORRECT, (2, 2): B.WRONG_CLASS, (3, 3): B.MISSED, (4, 4): B.FALSE_OCCUPIED}.items():
        r, c = grid.shape[0] - 1 - i, grid.shape[1] - 1 - j
        assert tuple(rgb[r, c]) == ERROR_COLORS[code]
    assert tuple(rgb[0, 0]) == ERROR_COLORS[B.EMPTY]


def test_error_map_respects_the_valid_mask_and_shapes(grid, palette):
    gt, pred = empty(grid), empty(grid)
    gt[2, 2, 2] = CAR
    valid = torch.ones(grid.shape, dtype=torch.bool)
    valid[2, 2, :] = False
    assert B.error_codes(gt, pred, palette, valid)[2, 2] == B.EMPTY
    with pytest.raises(ValueError, match="differ in shape"):
        B.error_codes(gt, pred[:-1], palette)


def test_column_mask_is_the_projection_of_the_mask(grid):
    mask = torch.zeros(grid.shape, dtype=torch.bool)
    mask[4, 7, 3] = True
    cols = B.column_mask(mask)
    assert cols.shape == grid.shape[:2] and cols.sum() == 1 and cols[4, 7]


def test_palette_colours_are_the_official_ones(palette):
    from occplug.data.classes import SEMANTIC_KITTI_CLASSES, SEMANTIC_KITTI_COLORS, class_colors

    assert tuple(palette.colors[CAR]) == (0, 150, 245)  # Occ3D car blue
    assert tuple(palette.colors[11]) == (255, 0, 255)  # driveable_surface magenta
    assert class_colors(SEMANTIC_KITTI_CLASSES) == SEMANTIC_KITTI_COLORS
    assert SEMANTIC_KITTI_COLORS[1] == (100, 150, 245)  # car, the yaml's BGR (245, 150, 100) as RGB
    assert len(SEMANTIC_KITTI_COLORS) == len(SEMANTIC_KITTI_CLASSES)
    other = class_colors(("a", "b", "c"))
    assert len(set(other)) == 3  # unknown taxonomies still get distinct colours
    assert palette.present(torch.tensor([CAR, FREE, 255, CAR, TRUCK])) == [CAR, TRUCK]
