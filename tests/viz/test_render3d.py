"""The 3D view: exact ray casting with empty-space skipping, look-at cameras, shaded faces."""

import numpy as np
import torch
from viz_helpers import CAR, empty

from occplug.geometry import GridSpec, first_hit, project_to_image
from occplug.viz.render3d import (
    FACE_SHADE,
    ViewCamera,
    cast_view,
    coarse_to_fine_first_hit,
    default_view,
    look_at,
    render_voxels,
)
from occplug.viz.style import BACKGROUND


def test_coarse_to_fine_equals_the_plain_traversal():
    gen = torch.Generator().manual_seed(0)
    grid = GridSpec((-3.0, -2.2, -1.0, 3.4, 2.2, 1.8), 0.4)  # 16 x 11 x 7: not a multiple of the block
    occ = torch.rand(grid.shape, generator=gen) < 0.08
    origins = torch.cat(
        [
            torch.rand(300, 3, generator=gen, dtype=torch.float64) * torch.tensor([6.4, 4.4, 2.8], dtype=torch.float64)
            + torch.tensor([-3.0, -2.2, -1.0], dtype=torch.float64),  # inside
            torch.randn(300, 3, generator=gen, dtype=torch.float64) * 8.0,  # mostly outside
        ]
    )
    dirs = torch.nn.functional.normalize(torch.randn(600, 3, generator=gen, dtype=torch.float64), dim=-1)
    dirs[:50, 2] = 0.0  # axis-parallel components too
    dirs = torch.nn.functional.normalize(dirs, dim=-1)
    ref_hit, ref_t = first_hit(occ, grid, origins, dirs, torch.inf)
    for block in (2, 4):
        hit, t = coarse_to_fine_first_hit(occ, grid, origins, dirs, block=block)
        assert torch.equal(hit, ref_hit)
        found = ref_hit[:, 0] >= 0
        assert found.sum() > 60
        assert torch.allclose(t[found], ref_t[found], atol=1e-9)
        assert torch.isinf(t[~found]).all()


def test_look_at_centres_the_target_with_up_up():
    view = ViewCamera(eye=(0.0, -10.0, 5.0), target=(1.0, 2.0, 0.0), width=64, height=48)
    k, pose = view.intrinsics(), view.cam_to_ego()
    pts = torch.tensor([[1.0, 2.0, 0.0], [1.0, 2.0, 1.0]], dtype=torch.float64)
    uv, depth = project_to_image(pts, k, pose)
    assert torch.allclose(uv[0], torch.tensor([31.5, 23.5], dtype=torch.float64), atol=1e-9)
    assert uv[1, 1] < uv[0, 1] and (depth > 0).all()  # higher in the world = higher in the image
    rot = pose[:3, :3]
    assert torch.allclose(rot.T @ rot, torch.eye(3, dtype=torch.float64), atol=1e-12)
    down = look_at(torch.tensor([0.0, 0.0, 10.0]), torch.tensor([0.0, 0.0, 0.0]))  # straight down
    assert torch.allclose(down[:3, 2], torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64))


def test_block_seen_from_above_shows_its_colour_on_its_top_face(grid, palette):
    labels = empty(grid)
    labels[4:7, 2:5, 0:3] = CAR  # 3 x 3 x 3; top face at z = 0.5, centre column (5, 3)
    centre_top = torch.tensor([[-2.25, -2.25, 0.5]], dtype=torch.float64)
    view = ViewCamera(eye=(-2.25, -2.25, 12.0), target=(-2.25, -2.25, 0.0), fov_deg=60, width=81, height=81)
    ((u, v),) = project_to_image(centre_top, view.intrinsics(), view.cam_to_ego())[0].round().long().tolist()
    image = render_voxels(labels, grid, palette, view, ego_box=False)
    assert tuple(image[v, u]) == tuple(palette.colors[CAR])  # top face: full brightness
    hits = cast_view(palette.occupied(labels.long()), grid, view, ego_box=False)
    assert hits.voxel[v, u].tolist() == [5, 3, 2] and hits.axis[v, u] == 2 and hits.sign[v, u] == 1
    assert torch.isclose(hits.distance[v, u], torch.tensor(11.5, dtype=torch.float64))
    assert tuple(image[0, 0]) == BACKGROUND  # outside the grid's floor: background


def test_default_view_from_behind_above_hits_the_block_with_a_shaded_face(grid, palette):
    labels = empty(grid)
    labels[12:15, 6:9, 1:4] = CAR
    view = default_view(grid, width=160, height=100)
    assert view.eye[0] < grid.lower[0] and view.eye[2] > grid.upper[2]  # behind and above
    centre = grid.index_to_coord(torch.tensor([13, 7, 2])).double()[None]
    ((u, v),) = project_to_image(centre, view.intrinsics(), view.cam_to_ego())[0].round().long().tolist()
    hits = cast_view(palette.occupied(labels.long()), grid, view, ego_box=False)
    i, j, k = hits.voxel[v, u].tolist()
    assert 12 <= i < 15 and 6 <= j < 9 and 1 <= k < 4
    assert (hits.axis[v, u].item(), hits.sign[v, u].item()) in FACE_SHADE
    pixel = render_voxels(labels, grid, palette, view, ego_box=False)[v, u].astype(float)
    color = palette.colors[CAR].astype(float)  # (0, 150, 245): a shade of car blue
    assert pixel[0] == 0 and abs(pixel[2] / pixel[1] - color[2] / color[1]) < 0.02
    assert 0.3 * color[2] < pixel[2] <= color[2]


def test_ego_box_is_drawn_and_empty_grid_renders(grid, palette):
    view = default_view(grid, width=96, height=60)
    image = render_voxels(empty(grid), grid, palette, view)
    assert image.shape == (60, 96, 3)
    ego = np.all(image[..., 1:] > 0, axis=-1) & (image[..., 0] == 0)  # shades of EGO_COLOR (0, 255, 127)
    assert 20 < ego.sum() < 0.2 * ego.size  # the ego, small, near the middle of the picture
    rows, cols = np.nonzero(ego)
    assert abs(cols.mean() - 47.5) < 5
