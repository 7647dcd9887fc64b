"""The Rerun recording reads back with rerun's own reader: entities, frames, voxel boxes."""

import gc
import weakref

import pytest
import torch
from viz_helpers import read_rrd

pytest.importorskip("rerun")
pytest.importorskip("matplotlib")

from occplug.viz.rerun_export import export_sequence, lidar_range_max, surface_voxels  # noqa: E402


def test_surface_voxels_drop_the_hidden_interior():
    occ = torch.zeros(5, 5, 5, dtype=torch.bool)
    occ[1:4, 1:4, 1:4] = True
    surface = surface_voxels(occ)
    assert surface.sum() == 26 and not surface[2, 2, 2]
    full = torch.ones(3, 3, 3, dtype=torch.bool)  # the grid's outside counts as free
    assert surface_voxels(full).sum() == 26


def test_sequence_recording_reads_back(tiny_dm, palette, tmp_path):
    ds = tiny_dm.dataset("val")
    frames = [ds[i] for i in range(len(ds))]
    assert len({f.scene for f in frames}) == 1 and len(frames) >= 2
    preds = [f.voxel_labels.clone() for f in frames]
    preds[0][:] = 17  # an empty prediction for frame 0: no boxes logged... but the entity exists
    preds[0][0, 0, 0] = 4
    path = export_sequence(frames, tmp_path / "seq.rrd", tiny_dm.grid, palette, predictions=preds)
    data = read_rrd(path)
    names = list(frames[0].camera_names)
    expected = {
        "/world",
        "/world/ego",
        "/world/ego_path",
        "/world/ego/lidar",
        "/world/ego/boxes",
        "/world/ego/occupancy/gt",
        "/world/ego/occupancy/pred",
        *(f"/world/ego/cameras/{n}" for n in names),
    }
    assert expected <= set(data)
    n = len(frames)
    for entity in expected - {"/world", "/world/ego_path"}:
        assert data[entity]["frames"] == set(range(n)), entity  # one row per frame on the 'frame' timeline
    assert not data["/world"]["frames"] and not data["/world/ego_path"]["frames"]  # static
    cam = data[f"/world/ego/cameras/{names[0]}"]["columns"]
    assert {"Pinhole:image_from_camera", "Image:buffer", "Transform3D:translation"} <= cam
    gt_counts = data["/world/ego/occupancy/gt"]["lengths"]["Boxes3D:class_ids"]
    assert sorted(gt_counts) == sorted(
        int(surface_voxels(palette.occupied(f.voxel_labels.long())).sum()) for f in frames
    )
    assert sorted(data["/world/ego/occupancy/pred"]["lengths"]["Boxes3D:class_ids"])[0] == 1
    boxes = data["/world/ego/boxes"]
    assert sorted(boxes["lengths"]["Boxes3D:labels"]) == sorted(len(f.boxes) for f in frames)
    assert "track_id" in {c.split(":")[-1] for c in boxes["columns"]}
    lidar = data["/world/ego/lidar"]["lengths"]["Points3D:positions"]
    assert sorted(lidar) == sorted(len(f.points) for f in frames)


def _lidar_colors(path) -> list[list[int]]:
    """Per logged row of ``/world/ego/lidar`` (in frame order), the packed point colours."""
    from rerun.chunk import RrdReader

    rows = []
    for chunk in RrdReader(str(path)).store().stream():
        if chunk.entity_path == "/world/ego/lidar":
            batch = chunk.to_record_batch()
            rows += zip(batch.column("frame").to_pylist(), batch.column("Points3D:colors").to_pylist(), strict=True)
    return [colors for _, colors in sorted(rows)]


def test_lidar_colours_use_one_range_scale_for_the_whole_recording(tiny_dm, palette, tmp_path):
    ds = tiny_dm.dataset("val")
    frames = [ds[i] for i in range(2)]
    for frame, far in zip(frames, (10.0, 30.0), strict=True):  # the same 5 m point, different farthest points
        points = torch.zeros(2, frame.points.shape[1], dtype=frame.points.dtype)
        points[0, 0], points[1, 0] = 5.0, far
        frame.points = points
    path = export_sequence(frames, tmp_path / "seq.rrd", tiny_dm.grid, palette)
    first, second = _lidar_colors(path)
    assert first[0] == second[0]  # a 5 m point has one colour in every frame
    assert first[1] != second[1]
    assert lidar_range_max(tiny_dm.grid) == 30.0  # the tiny grid's farthest corner: 23 m, rounded up


def test_frames_are_streamed_one_at_a_time(tiny_dm, palette, tmp_path):
    ds = tiny_dm.dataset("val")
    alive: list[weakref.ref] = []
    seen_alive: list[int] = []

    def tracked(frame):
        alive.append(weakref.ref(frame))
        return frame

    def frames():  # holds no frame itself while the exporter works
        for i in (0, 1, 0, 1):
            gc.collect()
            seen_alive.append(sum(r() is not None for r in alive))
            yield tracked(ds[i])

    predicted = []

    def predict(frame):
        predicted.append(frame.token)
        return frame.voxel_labels

    export_sequence(frames(), tmp_path / "seq.rrd", tiny_dm.grid, palette, predict=predict)
    assert seen_alive == [0, 0, 0, 0]  # no frame logged before is still held when the next is loaded
    assert predicted == [ds[i].token for i in (0, 1, 0, 1)]
    assert read_rrd(tmp_path / "seq.rrd")["/world/ego_path"]["lengths"]["LineStrips3D:strips"] == [1]


def test_prediction_count_must_match(tiny_dm, palette, tmp_path):
    frames = [tiny_dm.dataset("val")[0]] * 2
    with pytest.raises(ValueError, match="fewer predictions than frames"):
        export_sequence(frames, tmp_path / "a.rrd", tiny_dm.grid, palette, predictions=[None])
    with pytest.raises(ValueError, match="more predictions"):
        export_sequence(frames, tmp_path / "b.rrd", tiny_dm.grid, palette, predictions=[None] * 3)
    with pytest.raises(ValueError, match="at least one frame"):
        export_sequence(iter(()), tmp_path / "c.rrd", tiny_dm.grid, palette)
