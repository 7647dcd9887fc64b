"""Augmentation keeps geometry exact: LiDAR points land on pixels whose depth is theirs, before and after
every augmentation; BEV transforms move labels, points, boxes and poses together."""

import math

import pytest
import torch
import torch.nn.functional as F

from occplug.data import collate_frames
from occplug.data.augment import (
    PHOTOMETRIC_PRESETS,
    Augmentation,
    ImageTransform,
    apply_bev,
    apply_image_transforms,
    bev_matrix,
    crop_matrix,
    hflip_matrix,
    photometric,
    resize_matrix,
    rotate_matrix,
)
from occplug.data.synthetic import SyntheticDataset, default_cache_dir, preset
from occplug.data.synthetic.pseudo import SyntheticPseudoLabels
from occplug.geometry import invert_pose, project_to_image, unproject_from_image

TINY = preset("tiny")


@pytest.fixture(scope="module")
def frame():
    """A tiny-world frame with its noise-free pseudo depth (the GT depth resampled like any pseudo map)."""
    f = SyntheticDataset(TINY, "train", cache_dir=default_cache_dir())[0]
    return SyntheticPseudoLabels("perfect", kinds=("depth", "features")).attach(f)


def depth_agreement(f, field="depth"):
    """Share of projected LiDAR points whose depth lies within the depth-map values of their pixel's 3 x 3
    footprint (the landing pixel and the neighbours nearest-neighbour resampling may have drawn from)."""
    pts = f.points_in_ego()
    n = f.num_cameras
    uv, d = project_to_image(pts.expand(n, -1, -1), f.intrinsics, f.cam_to_ego, f.img_aug)
    dm = getattr(f, field)
    h, w = f.image_size
    hi = F.max_pool2d(dm[:, None], 3, 1, 1)[:, 0]
    lo = -F.max_pool2d(-torch.where(dm > 0, dm, torch.full_like(dm, 1e9))[:, None], 3, 1, 1)[:, 0]
    ok = total = 0
    for c in range(n):
        u, v = uv[c, :, 0].round().long(), uv[c, :, 1].round().long()
        m = (d[c] > 0.5) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        dc = d[c][m]
        good = (dc >= lo[c, v[m], u[m]] * 0.98 - 0.05) & (dc <= hi[c, v[m], u[m]] * 1.02 + 0.05)
        ok, total = ok + int(good.sum()), total + int(m.sum())
    assert total > 1000
    return ok / total


AUGMENTATIONS = {
    "flip": {"image": {"flip": 1.0}},
    "zoom_crop": {"image": {"size": [24, 48], "scale": [1.3, 1.4], "crop": "random"}},
    "shrink": {"image": {"size": [16, 32]}},
    "bottom_crop": {"image": {"size": [24, 64], "crop": "bottom"}},
    "rotate": {"image": {"rotate": [8.0, 12.0]}},
    "combined": {"image": {"size": [24, 48], "scale": [0.9, 1.3], "flip": 0.5, "rotate": [-10, 10]}},
    "bev": {"bev": {"flip_x": 0.5, "flip_y": 0.5, "rotate": [-30, 30], "scale": [0.9, 1.1]}},
    "weak": "weak",
    "middle": "middle",
    "strong": {"photometric": "strong", "image": {"size": [24, 48], "flip": 0.5}, "bev": {"flip_y": 1.0}},
}


@pytest.mark.parametrize("name", list(AUGMENTATIONS))
def test_lidar_points_land_on_pixels_with_their_depth_after_every_augmentation(frame, name):
    before = depth_agreement(frame)
    assert before > 0.97 and depth_agreement(frame, "pseudo_depth") > 0.97
    torch.manual_seed(0)
    aug = Augmentation(AUGMENTATIONS[name], grid=TINY.grid)
    for _ in range(2):
        out = aug(frame)
        assert depth_agreement(out) > 0.9, name
        assert depth_agreement(out, "pseudo_depth") > 0.9, name


def test_image_warp_is_the_recorded_matrix(frame):
    """Exactness: every augmented pixel holds the depth of the original pixel its centre maps back to, and the
    3D point seen there projects through the original calibration onto that original pixel."""
    h, w = frame.image_size
    a = hflip_matrix(48) @ rotate_matrix(7.0, (24, 48)) @ crop_matrix(3, 5) @ resize_matrix((h, w), (30, 60))
    t = ImageTransform((h, w), (30, 60), hflip_matrix(48) @ rotate_matrix(7.0, (24, 48)) @ crop_matrix(3, 5), (24, 48))
    assert torch.allclose(t.matrix, a)
    out = apply_image_transforms(frame, [t] * frame.num_cameras)
    assert torch.allclose(out.img_aug[0].double(), a.float().double(), atol=1e-5)
    v, u = torch.meshgrid(torch.arange(24.0), torch.arange(48.0), indexing="ij")
    uv = torch.stack([u, v], -1).reshape(-1, 2)
    src = torch.cat([uv, torch.ones(len(uv), 1)], -1).double() @ torch.linalg.inv(a).T
    su, sv = src[:, 0].round().long(), src[:, 1].round().long()
    inside = (su >= 0) & (su < w) & (sv >= 0) & (sv < h)
    for c in range(frame.num_cameras):
        dm = out.depth[c].reshape(-1)
        assert torch.equal(dm[inside], frame.depth[c][sv[inside], su[inside]])
        assert (dm[~inside] == 0).all()
        keep = inside & (dm > 0)
        ego = unproject_from_image(uv[keep], dm[keep], out.intrinsics[c], out.cam_to_ego[c], out.img_aug[c])
        back, _ = project_to_image(ego, frame.intrinsics[c], frame.cam_to_ego[c])
        assert torch.allclose(back, src[keep, :2].float(), atol=2e-3)
    assert out.pseudo_features.shape[-2:] == (6, 12)


def test_bev_augmentation_moves_everything_together(frame):
    grid = TINY.grid
    a = bev_matrix(flip_x=False, flip_y=True, yaw=0.0, scale=1.0)
    out = apply_bev(frame, a, grid)
    assert torch.equal(out.voxel_labels, frame.voxel_labels.flip(1))  # exact index flip of a symmetric grid
    assert torch.equal(out.mask_camera, frame.mask_camera.flip(1))
    a = bev_matrix(flip_x=True, yaw=math.radians(20), scale=1.1)
    out = apply_bev(frame, a, grid)
    a3 = a[:3, :3]
    # ego-frame points (through the new lidar_to_ego) are A times the old ones
    assert torch.allclose(out.points_in_ego().double(), frame.points_in_ego().double() @ a3.T, atol=1e-3)
    assert torch.allclose(out.boxes[:, :3].double(), frame.boxes[:, :3].double() @ a3.T, atol=1e-4)
    assert torch.allclose(out.boxes[:, 3:6], frame.boxes[:, 3:6] * 1.1, atol=1e-5)
    speed = lambda b: b[:, 7:9].norm(dim=1)  # noqa: E731
    assert torch.allclose(speed(out.boxes), speed(frame.boxes) * 1.1, atol=1e-4)
    # poses stay rigid (orthogonal rotation parts) and the depth maps scale with the world
    for pose in (out.cam_to_ego[0], out.lidar_to_ego, out.ego_to_global):
        r = pose[:3, :3].double()
        assert torch.allclose(r @ r.T, torch.eye(3, dtype=torch.float64), atol=1e-5)
    assert torch.allclose(out.depth, frame.depth * 1.1)
    assert torch.allclose(out.extras["bev_aug"], a)
    assert depth_agreement(out) > 0.97


def test_bev_augmentation_conjugates_relative_ego_motion():
    ds = SyntheticDataset(TINY.replace(adjacent_offsets=(-1,)), "train", cache_dir=default_cache_dir())
    f = ds[1]
    a = bev_matrix(flip_y=True, yaw=0.4, scale=0.9)
    out = apply_bev(f, a, TINY.grid)
    rel = invert_pose(f.ego_to_global) @ f.adjacent[-1].ego_to_global
    rel_aug = invert_pose(out.ego_to_global) @ out.adjacent[-1].ego_to_global
    assert torch.allclose(rel_aug, a @ rel @ torch.linalg.inv(a), atol=1e-6)
    assert torch.allclose(out.adjacent[-1].extras["bev_aug"], a)


def test_photometric_presets_change_pixels_only(frame):
    torch.manual_seed(0)
    assert set(PHOTOMETRIC_PRESETS) == {"none", "weak", "middle", "strong"}
    for name in ("weak", "middle", "strong"):
        out = Augmentation(name)(frame)
        assert out.images.shape == frame.images.shape and not torch.equal(out.images, frame.images)
        assert 0 <= float(out.images.min()) and float(out.images.max()) <= 1
        assert torch.equal(out.img_aug, frame.img_aug) and torch.equal(out.depth, frame.depth)
    batch = collate_frames([frame, frame])
    assert photometric(batch.images, "strong").shape == batch.images.shape  # a batch on any device


def test_augmentation_config_errors_name_the_key():
    with pytest.raises(ValueError, match=r"augment\.image\.flp: unknown key; did you mean 'flip'"):
        Augmentation({"image": {"flp": 0.5}})
    with pytest.raises(ValueError, match="unknown preset 'strongest'"):
        Augmentation("strongest")
    with pytest.raises(ValueError, match=r"augment\.bev\.scale"):
        Augmentation({"bev": {"scale": [1.2, 0.8]}})


def test_projection_honours_a_rotated_img_aug(frame):
    """``project_to_image`` uses the full ``A @ K`` (a rotation puts off-diagonal terms in it)."""
    a = rotate_matrix(25.0, frame.image_size).float()
    pts = frame.points_in_ego()[:50]
    uv, depth = project_to_image(pts, frame.intrinsics[0], frame.cam_to_ego[0], a)
    cam = (pts - frame.cam_to_ego[0][:3, 3]) @ frame.cam_to_ego[0][:3, :3]
    hom = cam @ (a @ frame.intrinsics[0]).T
    front = depth > 0.5
    assert torch.allclose(uv[front], (hom[:, :2] / hom[:, 2:3])[front], atol=1e-3)
    back = unproject_from_image(uv[front], depth[front], frame.intrinsics[0], frame.cam_to_ego[0], a)
    assert torch.allclose(back, pts[front], atol=1e-3)


def test_lidar_dropout_and_jitter_are_recorded_and_replayable(frame):
    from occplug.data.augment import apply_lidar

    aug = Augmentation({"lidar": {"dropout": 0.25, "jitter": 0.05}})
    assert aug.active
    g = torch.Generator().manual_seed(3)
    out = aug(frame, generator=g)
    rec = out.extras["lidar_aug"]
    keep, offset = rec["keep"], rec["offset"]
    p = frame.points.shape[0]
    assert keep.shape == (p,) and keep.dtype == torch.bool
    assert 0.7 < float(keep.float().mean()) < 0.8  # dropout 0.25 of thousands of points
    assert out.points.shape == (int(keep.sum()), 4) and out.point_labels.shape == (int(keep.sum()),)
    # the record is what happened: kept points moved by the offset, intensity and labels untouched
    assert torch.equal(out.points[:, :3], frame.points[keep][:, :3] + offset)
    assert torch.equal(out.points[:, 3], frame.points[keep][:, 3])
    assert torch.equal(out.point_labels, frame.point_labels[keep])
    assert abs(float(offset.std()) - 0.05) < 0.005
    # replaying the record on the original frame reproduces the augmented scan exactly
    again = apply_lidar(frame, keep, offset)
    assert torch.equal(again.points, out.points) and torch.equal(again.point_labels, out.point_labels)
    # the same generator seed draws the same augmentation; the original frame is untouched
    same = aug(frame, generator=torch.Generator().manual_seed(3))
    assert torch.equal(same.points, out.points)
    assert frame.points.shape[0] == p and "lidar_aug" not in frame.extras
    # images, poses and voxels are untouched by a LiDAR-only augmentation
    assert torch.equal(out.images, frame.images) and torch.equal(out.voxel_labels, frame.voxel_labels)
    # zero dropout and jitter: the identity, still recorded
    ident = Augmentation({"lidar": {}})(frame)
    assert torch.equal(ident.points, frame.points) and bool(ident.extras["lidar_aug"]["keep"].all())
    with pytest.raises(ValueError, match=r"augment.lidar.dropout: expected a probability in \[0, 1\)"):
        Augmentation({"lidar": {"dropout": 1.5}})
    with pytest.raises(ValueError, match="augment.lidar"):
        Augmentation({"lidar": {"jiter": 0.1}})
    with pytest.raises(ValueError, match="does not fit"):
        apply_lidar(frame, keep[:-1], offset)


def test_lidar_augmentation_happens_in_the_lidar_frame_before_the_bev_transform(frame):
    g = torch.Generator().manual_seed(0)
    out = Augmentation({"lidar": {"dropout": 0.5, "jitter": 0.1}, "bev": {"scale": [2.0, 2.0]}}, TINY.grid)(
        frame, generator=g
    )
    rec = out.extras["lidar_aug"]
    # the BEV scale applies to the jittered points: xyz = 2 * (original + offset)
    assert torch.allclose(out.points[:, :3], 2 * (frame.points[rec["keep"]][:, :3] + rec["offset"]), atol=1e-5)
