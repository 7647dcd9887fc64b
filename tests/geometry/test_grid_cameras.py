import math

import pytest
import torch

from occplug.geometry import (
    GridSpec,
    camera_rays,
    contract,
    lidar_ray_directions,
    make_pose,
    project_to_image,
    sample_volume,
    uncontract,
    unproject_from_image,
    warp_volume,
)

# A camera 1.5 m up at x = 1 looking along ego +x: camera z = ego x, camera x = -ego y, camera y = -ego z.
FORWARD = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
K = torch.tensor([[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]])


def cam_to_ego() -> torch.Tensor:
    return make_pose(FORWARD, torch.tensor([1.0, 0.0, 1.5]))


def test_grid_shape_and_index_coord_round_trip():
    g = GridSpec(range=(-40, -40, -1, 40, 40, 5.4), voxel_size=0.4)
    assert g.shape == (200, 200, 16)
    idx = torch.stack([torch.randint(0, n, (500,)) for n in g.shape], -1)
    assert torch.equal(g.coord_to_index(g.index_to_coord(idx)), idx)
    assert torch.allclose(g.index_to_coord(torch.tensor([0, 0, 0])), torch.tensor([-39.8, -39.8, -0.8]))
    assert g.contains(torch.tensor([39.99, -40.0, 5.39])) and not g.contains(torch.tensor([40.0, 0.0, 0.0]))


def test_grid_rejects_bad_specs():
    with pytest.raises(ValueError, match="multiple of voxel size"):
        GridSpec(range=(0, 0, 0, 1, 1, 1), voxel_size=0.3)
    with pytest.raises(ValueError, match="max must exceed min"):
        GridSpec(range=(0, 0, 0, -1, 1, 1), voxel_size=0.5)


def test_projection_known_value():
    uv, depth = project_to_image(torch.tensor([[11.0, 0.0, 1.5], [11.0, -1.0, 0.5]]), K, cam_to_ego())
    # straight ahead -> principal point; 1 m right and 1 m down at 10 m depth -> +10 px each
    assert torch.allclose(uv, torch.tensor([[50.0, 40.0], [60.0, 50.0]]))
    assert torch.allclose(depth, torch.tensor([10.0, 10.0]))


def test_project_unproject_round_trip_with_augmentation():
    gen = torch.Generator().manual_seed(0)
    pts = torch.rand(2, 3, 50, 3, generator=gen) * torch.tensor([20.0, 10.0, 3.0]) + torch.tensor([3.0, -5.0, 0.0])
    k = K.expand(2, 3, 3, 3)
    c2e = cam_to_ego().expand(2, 3, 4, 4)
    # resize by 0.5, then flip horizontally within a 50-px-wide image, then crop 4 px from the top
    aug = torch.tensor([[-0.5, 0.0, 49.0], [0.0, 0.5, -4.0], [0.0, 0.0, 1.0]]).expand(2, 3, 3, 3)
    uv, depth = project_to_image(pts, k, c2e, aug)
    back = unproject_from_image(uv, depth, k, c2e, aug)
    assert torch.allclose(back, pts, atol=1e-4)
    uv_plain, _ = project_to_image(pts, k, c2e)
    expected = torch.stack([49.0 - 0.5 * uv_plain[..., 0], 0.5 * uv_plain[..., 1] - 4.0], -1)
    assert torch.allclose(uv, expected, atol=1e-4)


def test_camera_rays_pass_through_pixels():
    origins, dirs, z_per_metre = camera_rays(K, cam_to_ego(), 80, 100)
    assert torch.allclose(origins, torch.tensor([1.0, 0.0, 1.5]))
    pts = origins + dirs[17, 63] * 12.0
    uv, depth = project_to_image(pts[None], K, cam_to_ego())
    assert torch.allclose(uv[0], torch.tensor([63.0, 17.0]), atol=1e-4)
    assert math.isclose(float(depth[0]), 12.0 * float(z_per_metre[17, 63]), rel_tol=1e-5)
    assert torch.allclose(dirs.norm(dim=-1), torch.ones(80, 100))


def test_sample_volume_reads_voxel_centres_and_interpolates():
    g = GridSpec(range=(-2, -2, -1, 2, 2, 1), voxel_size=0.5)
    vol = torch.randn(2, 3, *g.shape)
    idx = torch.tensor([[0, 0, 0], [7, 3, 2], [4, 5, 3]])
    pts = g.index_to_coord(idx)[None].expand(2, -1, -1)
    out = sample_volume(vol, g, pts)
    assert torch.allclose(out, vol[:, :, idx[:, 0], idx[:, 1], idx[:, 2]].transpose(1, 2), atol=1e-6)
    mid = (g.index_to_coord(torch.tensor([2, 2, 2])) + g.index_to_coord(torch.tensor([3, 2, 2]))) / 2
    expected = (vol[:, :, 2, 2, 2] + vol[:, :, 3, 2, 2]) / 2
    assert torch.allclose(sample_volume(vol, g, mid.expand(2, 1, 3))[:, 0], expected, atol=1e-6)


def test_warp_volume_by_whole_voxel_translation():
    g = GridSpec(range=(-4, -4, -1, 4, 4, 1), voxel_size=1.0)
    vol = torch.randn(1, 2, *g.shape)
    # the destination frame is 2 m ahead of the source: a point at x in src is at x - 2 in dst
    src_to_dst = make_pose(torch.eye(3), torch.tensor([-2.0, 0.0, 0.0]))[None]
    out = warp_volume(vol, g, src_to_dst)
    assert torch.allclose(out[:, :, :6], vol[:, :, 2:], atol=1e-6)
    assert torch.all(out[:, :, 6:] == 0)


@pytest.mark.parametrize("kappa", [0.3, 0.5, 0.8])
def test_contraction_round_trip_and_continuity(kappa):
    x = torch.linspace(-200, 200, 4001, dtype=torch.float64)
    y = contract(x, near=10.0, kappa=kappa)
    assert y.abs().max() < 1 and torch.all(y[1:] > y[:-1])
    assert torch.allclose(uncontract(y, near=10.0, kappa=kappa), x, atol=1e-8)
    assert math.isclose(float(contract(torch.tensor(10.0), 10.0, kappa)), kappa, rel_tol=1e-6)
    assert math.isclose(float(contract(torch.tensor(20.0), 10.0, kappa)), 1 - (1 - kappa) / 2, rel_tol=1e-6)


def test_lidar_ray_directions_known_values():
    dirs = lidar_ray_directions(torch.tensor([-30.0, 0.0, 10.0]), 4)
    assert dirs.shape == (3, 4, 3)
    assert torch.allclose(dirs.norm(dim=-1), torch.ones(3, 4))
    assert torch.allclose(dirs[1, 1], torch.tensor([0.0, 1.0, 0.0]), atol=1e-6)  # azimuth 90 deg: +y
    el = math.radians(-30)
    assert torch.allclose(dirs[0, 2], torch.tensor([-math.cos(el), 0.0, math.sin(el)]), atol=1e-6)
