import math

import torch

from occplug.geometry import invert_pose, make_pose, relative_pose, rotation_z, transform_points, wrap_angle, yaw_of


def random_pose(gen: torch.Generator, batch: int = 4) -> torch.Tensor:
    q = torch.randn(batch, 4, generator=gen, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rot = torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            torch.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            torch.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )
    return make_pose(rot, torch.randn(batch, 3, generator=gen, dtype=torch.float64) * 10)


def test_invert_pose_round_trip():
    gen = torch.Generator().manual_seed(0)
    pose = random_pose(gen)
    eye = torch.eye(4, dtype=torch.float64).expand(4, 4, 4)
    assert torch.allclose(pose @ invert_pose(pose), eye, atol=1e-12)
    assert torch.allclose(invert_pose(pose), torch.linalg.inv(pose), atol=1e-10)


def test_relative_pose_maps_points_between_frames():
    gen = torch.Generator().manual_seed(1)
    a_to_g, b_to_g = random_pose(gen, 1), random_pose(gen, 1)
    pts_a = torch.randn(1, 20, 3, generator=gen, dtype=torch.float64)
    pts_g = transform_points(a_to_g, pts_a)
    pts_b = transform_points(invert_pose(b_to_g), pts_g)
    assert torch.allclose(transform_points(relative_pose(a_to_g, b_to_g), pts_a), pts_b, atol=1e-10)


def test_rotation_z_known_value_and_yaw():
    rot = rotation_z(torch.tensor(math.pi / 2))
    assert torch.allclose(rot @ torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 1, 0]), atol=1e-6)
    pose = make_pose(rotation_z(torch.tensor(0.7)), torch.zeros(3))
    assert math.isclose(float(yaw_of(pose)), 0.7, abs_tol=1e-6)
    assert math.isclose(float(wrap_angle(torch.tensor(2.5 * math.pi))), 0.5 * math.pi, abs_tol=1e-6)
    assert math.isclose(float(wrap_angle(torch.tensor(-1.5 * math.pi))), 0.5 * math.pi, abs_tol=1e-6)


def test_transform_points_unbatched_pose():
    pose = make_pose(rotation_z(torch.tensor(math.pi)), torch.tensor([1.0, 2.0, 3.0]))
    out = transform_points(pose, torch.tensor([[1.0, 0.0, 0.0]]))
    assert torch.allclose(out, torch.tensor([[0.0, 2.0, 3.0]]), atol=1e-6)
