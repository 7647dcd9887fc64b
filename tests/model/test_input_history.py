"""``model.input_history``: past frames encoded with their sensors moved into the current ego frame."""

import dataclasses

import pytest
import torch

from occplug import export as ex
from occplug.geometry import transform_points
from occplug.model import frame_in_current_ego
from occplug.run import runner

BASELINE = ["configs/baseline.yaml"]
TINY = ["data.preset=tiny", "data.adjacent_offsets=[-1]"]


@pytest.fixture(scope="module")
def dm():
    return runner.build_datamodule(runner.load_config(BASELINE, TINY))


def _batch(dm, indices=(2, 3)):
    data = dm.dataset("train")
    return dm.collate([data[i] for i in indices])


def test_moved_sensors_map_past_observations_to_where_they_are_now(dm):
    batch = _batch(dm)
    past = batch.adjacent[-1]
    moved = frame_in_current_ego(batch, -1)
    step = (past.ego_to_global[:, :3, 3] - batch.ego_to_global[:, :3, 3]).norm(dim=-1)
    assert bool((step > 0.1).any())  # the ego moved between the frames (a scene's first frame is its own -1)
    for b in range(len(batch)):
        pts = past.points[b][:, :3].double()
        # lidar -> past ego -> global -> current ego, written out
        world = transform_points(past.ego_to_global[b].double() @ past.lidar_to_ego[b].double(), pts)
        expected = transform_points(torch.linalg.inv(batch.ego_to_global[b].double()), world)
        got = transform_points(moved.lidar_to_ego[b].double(), pts)
        torch.testing.assert_close(got, expected, rtol=0, atol=1e-4)
        cam = torch.linalg.inv(batch.ego_to_global[b].double()) @ past.ego_to_global[b].double() @ past.cam_to_ego[b].double()
        torch.testing.assert_close(moved.cam_to_ego[b].double(), cam, rtol=0, atol=1e-5)
    assert torch.equal(moved.ego_to_global, batch.ego_to_global) and torch.equal(moved.images, past.images)


def test_the_previous_lidar_moved_lands_on_the_current_frames_occupied_voxels(dm):
    """A mostly static world: moved, the previous sweep hits voxels the current labels call occupied; unmoved
    (the past ego frame taken for the current one), it misses several times more often."""
    batch = _batch(dm, indices=(2, 3, 4, 5))
    free = dm.free_label
    grid = runner.build_model(runner.load_config(BASELINE, TINY), dm).grid
    moved, past = frame_in_current_ego(batch, -1), batch.adjacent[-1]

    def hit_rate(lidar_to_ego):
        hits = total = 0
        for b in range(len(batch)):
            xyz = transform_points(lidar_to_ego[b].to(past.points[b].dtype), past.points[b][:, :3])
            idx = grid.coord_to_index(xyz)
            inside = grid.contains(xyz) & grid.index_in_bounds(idx)
            labels = batch.voxel_labels[b][tuple(idx[inside].t())]
            hits, total = hits + int((labels != free).sum()), total + int(inside.sum())
        return hits / total

    moved_miss, unmoved_miss = 1 - hit_rate(moved.lidar_to_ego), 1 - hit_rate(past.lidar_to_ego)
    assert moved_miss < 0.05 and moved_miss < unmoved_miss / 3


def test_model_encodes_each_history_frame_on_the_current_grid(dm):
    cfg = runner.load_config(BASELINE, [*TINY, "model.input_history=[-1]"])
    model = runner.build_model(cfg, dm).eval()
    batch = _batch(dm)
    with torch.no_grad():
        out = model(batch)
        alone = runner.build_model(runner.load_config(BASELINE, TINY), dm)
        alone.load_state_dict(model.state_dict())
        ref = alone.eval()(batch)
        past = alone(dataclasses.replace(frame_in_current_ego(batch, -1), adjacent={}))
    assert list(out.history) == [-1]
    torch.testing.assert_close(out.history[-1].lifted.volume, past.lifted.volume)
    torch.testing.assert_close(out.lifted.volume, ref.lifted.volume)  # the current frame is untouched
    assert float((out.history[-1].lifted.volume - out.lifted.volume).abs().max()) > 1e-4


def test_history_mistakes_are_one_line(dm):
    with pytest.raises(ValueError, match=r"model.input_history: frame offsets other than 0, each once"):
        runner.build_model(runner.load_config(BASELINE, [*TINY, "model.input_history=[0]"]), dm)
    cfg = runner.load_config(BASELINE, ["data.preset=tiny", "model.input_history=[-2]"])
    model = runner.build_model(cfg, runner.build_datamodule(cfg))
    with pytest.raises(ValueError, match=r"frame offset -2 is not loaded; set data.adjacent_offsets"):
        model(_batch(dm))
    with pytest.raises(ex.ExportError, match=r"^model.input_history \[-2\]: the exported graph takes one frame"):
        ex.check_exportable(model)
