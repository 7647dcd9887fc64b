"""The synthetic world's ideal field, label-only frames, the issue-52 world knobs and the testbed measurement."""

import math

import pytest
import torch

from occplug.ceilings import read_voxels
from occplug.data.label_fraction import LabelCut
from occplug.data.sequences import SceneIndex
from occplug.data.synthetic import SyntheticDataModule, build_scene, generate_frame, preset
from occplug.data.synthetic.field import field_samples
from occplug.data.synthetic.frames import frame_labels
from occplug.data.synthetic.labels import voxel_labels
from occplug.data.synthetic.primitives import BOX, Primitives
from occplug.data.synthetic.render import LidarSweep, corrupt_lidar, lidar_generator
from occplug.data.synthetic.testbed import _box_corners, measure, object_pixel_heights
from occplug.data.synthetic.world import GroundMap
from occplug.geometry import GridSpec

TINY = preset("tiny")
FREE, CAR, ROAD = 17, 4, 11


def _ground(label: int = ROAD) -> GroundMap:
    return GroundMap(torch.full((4, 4), label, dtype=torch.uint8), (-100.0, -100.0), 50.0, torch.zeros(0, 8))


def _box(center, half, label=CAR) -> Primitives:
    return Primitives.from_rows(
        [{"shape": BOX, "center": center, "half": half, "label": label, "material": 0, "color": (0.5, 0.5, 0.5)}]
    )


def test_field_of_a_hand_made_world_at_centres_and_sub_samples():
    """1 m voxels, z from -1. A box filling x, y in [0.1, 0.9] and z in [0.1, 0.9] of voxel (0, 0, 1), and a box
    grazing voxel (1, 0, 1) over its first 0.2 m in x; ground (road) as a 0.5 m slab below z = 0."""
    grid = GridSpec((0.0, 0.0, -1.0, 2.0, 1.0, 2.0), 1.0)
    prims = Primitives.cat([_box((0.5, 0.5, 0.5), (0.4, 0.4, 0.4)), _box((1.1, 0.5, 0.5), (0.1, 0.4, 0.4))])
    pose = torch.eye(4, dtype=torch.float64)
    centre = field_samples(prims, _ground(), pose, grid, 1)[..., 0, 0, 0]
    # layer 0's centre z = -0.5 lies on the slab's lower face (closed): road
    assert centre[0, 0].tolist() == [ROAD, CAR, FREE]
    assert centre[1, 0].tolist() == [ROAD, FREE, FREE]  # the grazing box misses the centre (1.5, 0.5, 0.5)
    samples = field_samples(prims, _ground(), pose, grid, 4)
    anyr = read_voxels(samples, "any", FREE, 18)
    assert anyr[:, 0, 1].tolist() == [CAR, CAR]  # 4^3 sub-samples at x = 1.125 fall inside the grazing box
    assert anyr[:, 0, 0].tolist() == [ROAD, ROAD]  # sub-samples at z = -0.375, -0.125 are in the slab
    # exact counts: the first box holds sub-samples at 0.125..0.875 -> 4^3 of voxel (0,0,1); the grazing one
    # x = 1.125 only (1.0 < x <= 1.2) -> 16 of 64
    assert int((samples[0, 0, 1] == CAR).sum()) == 64 and int((samples[1, 0, 1] == CAR).sum()) == 16
    # labels (touch rule) agree with the any-readout here, not with the centre readout
    labels = voxel_labels(prims, _ground(), pose, grid, 4)
    assert labels[1, 0, 1] == CAR and centre[1, 0, 1] == FREE


def test_ground_on_a_voxel_centre_is_read_as_ground():
    """z from -1.5 at 1 m puts z = 0 on the centre of layer 1: the centre readout reads the road there."""
    grid = GridSpec((0.0, 0.0, -1.5, 1.0, 1.0, 1.5), 1.0)
    centre = field_samples(Primitives.empty(), _ground(), torch.eye(4, dtype=torch.float64), grid, 1)
    assert centre[0, 0, :, 0, 0, 0].tolist() == [FREE, ROAD, FREE]
    none = field_samples(Primitives.empty(), _ground(), torch.eye(4, dtype=torch.float64), grid, 1, ground_shell=0)
    assert (none == FREE).all()


def test_frame_labels_equal_the_rendered_frame():
    scene = build_scene(TINY, "val", 0)
    frame = generate_frame(TINY, scene, "val", 0, 1)
    lab = frame_labels(TINY, scene, 1)
    assert torch.equal(lab.voxel_labels, frame.voxel_labels)
    assert torch.equal(lab.mask_camera, frame.mask_camera) and torch.equal(lab.mask_lidar, frame.mask_lidar)
    front = frame_labels(TINY, scene, 1, num_cameras=1).mask_camera
    assert front.sum() < lab.mask_camera.sum() and not (front & ~lab.mask_camera).any()


def _sweep(n: int = 20000) -> LidarSweep:
    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    r = 5 + 30 * torch.rand(n, 1, generator=g)
    return LidarSweep(torch.cat([d * r, torch.rand(n, 1, generator=g)], -1), torch.arange(n), torch.zeros(3))


def test_lidar_corruption_noise_along_the_ray_and_dropout():
    sweep = _sweep()
    assert corrupt_lidar(sweep, 0.0, 0.0, torch.Generator()) is sweep
    noisy = corrupt_lidar(sweep, 0.05, 0.0, torch.Generator().manual_seed(1))
    r0, r1 = sweep.points[:, :3].norm(dim=-1), noisy.points[:, :3].norm(dim=-1)
    assert (r1 - r0).std().item() == pytest.approx(0.05, rel=0.05)
    cos = torch.nn.functional.cosine_similarity(sweep.points[:, :3], noisy.points[:, :3], dim=-1)
    assert (cos > 1 - 1e-5).all()  # along each ray
    assert torch.equal(noisy.points[:, 3], sweep.points[:, 3])
    dropped = corrupt_lidar(sweep, 0.0, 0.25, torch.Generator().manual_seed(1))
    assert dropped.points.shape[0] / sweep.points.shape[0] == pytest.approx(0.75, abs=0.02)
    keep = dropped.labels  # labels follow their points (labels here are the row numbers)
    assert torch.equal(dropped.points, sweep.points[keep])


def test_lidar_knobs_change_only_the_sweep_and_keep_old_cache_keys():
    assert TINY.replace(lidar_range_noise=0.0, lidar_dropout=0.0).cache_key() == TINY.cache_key()
    assert TINY.replace(ego_lane_speed_offset=(0, 0)).cache_key() == TINY.cache_key()
    noisy = TINY.replace(lidar_range_noise=0.02, lidar_dropout=0.1)
    assert noisy.cache_key() != TINY.cache_key()
    scene = build_scene(TINY, "train", 0)
    a, b = generate_frame(TINY, scene, "train", 0, 0), generate_frame(noisy, scene, "train", 0, 0)
    assert torch.equal(a.images, b.images) and torch.equal(a.voxel_labels, b.voxel_labels)
    assert b.points.shape[0] == pytest.approx(0.9 * a.points.shape[0], rel=0.03)
    again = generate_frame(noisy, scene, "train", 0, 0)
    assert torch.equal(again.points, b.points)  # seeded per frame
    assert lidar_generator(scene, 0).initial_seed() != lidar_generator(scene, 1).initial_seed()
    for bad in ({"lidar_range_noise": -1.0}, {"lidar_dropout": 1.0}, {"ego_lane_speed_offset": (3.0, 1.0)}):
        with pytest.raises(ValueError):
            TINY.replace(**bad)


def _ego_lane(config, scene):
    ego_y = scene.ego.start[1]
    lane = (scene.agents.start[:, 1] - ego_y).abs() < 1e-6
    return lane & (scene.agents.heading.abs() < 1e-9)


def test_ego_lane_traffic_with_its_own_speed():
    base = TINY.replace(vehicle_density=12.0)
    fast = base.replace(ego_lane_speed_offset=(2.0, 2.0))
    for index in range(3):
        s0, s1 = build_scene(base, "train", index), build_scene(fast, "train", index)
        lane0, lane1 = _ego_lane(base, s0), _ego_lane(fast, s1)
        if not lane1.any():
            continue
        assert torch.allclose(s0.agents.speed[lane0], torch.full_like(s0.agents.speed[lane0], s0.ego.speed))
        ahead = s1.agents.start[:, 0] > s1.ego.start[0]
        assert torch.allclose(s1.agents.speed[lane1 & ahead], torch.tensor(s1.ego.speed + 2.0, dtype=torch.float64))
        assert torch.allclose(
            s1.agents.speed[lane1 & ~ahead], torch.tensor(max(0.0, s1.ego.speed - 2.0), dtype=torch.float64)
        )
        return
    pytest.fail("no scene with ego-lane traffic")


def test_label_fraction_by_whole_scenes():
    scenes = SceneIndex.regular([f"s{i}" for i in range(4)], 3)
    cut = LabelCut(0.5, unit="scene")
    assert sorted(cut.unlabelled(12, scenes)) == [3, 4, 5, 9, 10, 11]  # scenes 0 and 2 keep their labels
    assert cut.selected(12, scenes) == list(range(12))
    assert LabelCut(0.5, "labelled", unit="scene").selected(12, scenes) == [0, 1, 2, 6, 7, 8]
    assert sorted(LabelCut(0.5).unlabelled(12)) == [1, 3, 5, 7, 9, 11]  # by interval, for contrast
    assert LabelCut(0.5, unit="scene").describe()["label_unit"] == "scene"
    with pytest.raises(ValueError, match="data.label_unit"):
        LabelCut(0.5, unit="clip")
    with pytest.raises(ValueError, match="scene structure"):
        cut.unlabelled(12)


def test_datamodule_label_unit_and_long_evaluation_scenes():
    dm = SyntheticDataModule(preset="tiny", label_fraction=0.5, label_unit="scene", eval_frames_per_scene=4)
    assert dm.world_config.frames("val") == 4 and dm.world_config.frames("train") == 3
    train = dm.dataset("train")
    flags = [train[i].has_voxel_labels for i in range(len(train))]
    assert flags == [True, True, True, False, False, False]  # tiny: 2 scenes x 3 frames; scene 0 labelled


def test_box_corners_and_pixel_heights_scale_with_the_image():
    box = torch.tensor([[10.0, 0.0, 1.0, 4.0, 2.0, 2.0, math.pi / 2]])
    c = _box_corners(box)
    assert torch.allclose(c.amin(1), torch.tensor([[9.0, -2.0, 0.0]])) and torch.allclose(
        c.amax(1), torch.tensor([[11.0, 2.0, 2.0]])
    )
    small = object_pixel_heights(TINY, "train", scenes=1)
    big = object_pixel_heights(TINY.replace(image_size=(64, 128)), "train", scenes=1)
    assert small and set(small) == set(big)
    for cls in small:
        assert small[cls]["count"] == big[cls]["count"]
        assert big[cls]["median_px"] / small[cls]["median_px"] == pytest.approx(2.0, rel=0.1)


def test_measure_on_the_tiny_world():
    r = measure(TINY, readouts=("center", "any2"), depth_stride=4, train_scenes=1, eval_scenes=1)
    assert r["frames"] == TINY.frames("val")
    assert r["floor"]["camera"]["all free"]["IoU"] == 0.0
    # the ideal field read at 2^3 sub-samples beats the centre readout under every mask (the touch-rule labels)
    for mask in ("camera", "lidar", "none"):
        assert r["ideal"][mask]["any2"]["IoU"] > r["ideal"][mask]["center"]["IoU"]
    h = r["headroom"]
    assert h["rig_camera_mask"]["earlier_only"] == 0 and h["rig_camera_mask"]["share_observed_now"] == 100.0
    assert h["front_all_voxels"]["scored"] == math.prod(TINY.grid.shape) * TINY.frames("val")
    assert h["front_all_voxels"]["earlier_only"] > 0
    assert r["perfect_depth"]["camera"]["rig"]["IoU"] > 0
    with pytest.raises(ValueError, match="unknown mask"):
        measure(TINY, masks=("cam",))
