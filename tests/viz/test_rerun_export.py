"""The Rerun recording reads back with rerun's own reader: entities, frames, voxel boxes."""

import pytest
import torch
from viz_helpers import read_rrd

pytest.importorskip("rerun")
pytest.importorskip("matplotlib")

from occplug.viz.rerun_export import export_sequence, surface_voxels  # noqa: E402


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
