"""The detector's k-means anchors (the public code's anchor generator) and occplug_duocc.tools.fit_anchors."""

import pytest
import torch
import yaml

from occplug.run import runner
from occplug_duocc.blocks.detector import SparseDetector
from occplug_duocc.tools import fit_anchors
from occplug_duocc.tools.anchors import kmeans, kmeans_anchors


def test_kmeans_recovers_separated_clusters_deterministically():
    gen = torch.Generator().manual_seed(3)
    truth = torch.tensor([[-10.0, 5.0, 1.0], [0.0, -8.0, 0.5], [12.0, 3.0, 1.5]])
    points = torch.cat([c + 0.1 * torch.randn(40, 3, generator=gen) for c in truth])
    points = points[torch.randperm(len(points), generator=gen)]
    centres = kmeans(points, 3, seed=0)
    assert torch.allclose(centres, truth.double(), atol=0.05)  # sorted by x, like truth
    assert torch.equal(centres, kmeans(points, 3, seed=0))
    assert torch.allclose(kmeans(points, 3, seed=7), centres)  # another seeding, the same minimum here
    # each centre is the mean of the points nearest to it (Lloyd's fixed point)
    nearest = torch.cdist(points.double(), centres).argmin(1)
    for c in range(3):
        assert torch.allclose(centres[c], points.double()[nearest == c].mean(0))
    with pytest.raises(ValueError, match="M >= k"):
        kmeans(points[:2], 3)


def test_kmeans_with_more_clusters_than_distinct_points_stays_finite():
    points = torch.tensor([[0.0, 0.0, 0.0]] * 3 + [[10.0, 0.0, 0.0], [20.0, 0.0, 0.0]])
    centres = kmeans(points, 4, seed=1)
    assert torch.isfinite(centres).all()
    # every centre is one of the three distinct points, and each of them is a centre
    distinct = torch.tensor([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [20.0, 0.0, 0.0]], dtype=torch.float64)
    assert (torch.cdist(centres, distinct).amin(1) == 0).all() and (torch.cdist(distinct, centres).amin(1) == 0).all()


def test_kmeans_anchors_take_the_mean_box_size():
    boxes = torch.tensor([[0.0, 0.0, 1.0, 4.0, 2.0, 1.5], [10.0, 0.0, 1.0, 1.0, 1.0, 2.0]])
    centres, size = kmeans_anchors(boxes, 2)
    assert torch.allclose(centres, boxes[:, :3].double())
    assert torch.allclose(size, torch.tensor([2.5, 1.5, 1.75], dtype=torch.float64))


def test_detector_starts_at_the_given_centres_and_names_a_count_mismatch():
    centres = [[float(i), -float(i), 0.5 + 0.1 * i] for i in range(6)]
    det = SparseDetector(num_classes=3, channels=32, num_queries=6, num_temporal=2, anchor_centres=centres)
    assert torch.allclose(det.anchors[:, :3], torch.tensor(centres))
    assert torch.allclose(det.anchors[:, 3:6].exp(), torch.tensor([4.0, 1.8, 1.6]).expand(6, 3))
    with pytest.raises(ValueError, match="anchor_centres must be num_queries=8 rows"):
        SparseDetector(num_classes=3, channels=32, num_queries=8, num_temporal=2, anchor_centres=centres)


def test_fit_anchors_writes_an_overlay_the_full_model_starts_from(tmp_path, capsys):
    out = tmp_path / "anchors.yaml"
    assert fit_anchors.main(["-c", "duocc/full", "data.preset=tiny", "--queries", "30", "--out", str(out)]) == 0
    detector = yaml.safe_load(out.read_text())["model"]["scene"]["query_agg"]["detector"]
    assert detector["num_queries"] == 30 and len(detector["anchor_centres"]) == 30
    cfg = runner.load_config(["duocc/full", str(out)], ["data.preset=tiny"])
    dm, model = runner.build_run(cfg)
    anchors = model.scene.query_agg.detector.anchors.detach()
    assert torch.allclose(anchors[:, :3], torch.tensor(detector["anchor_centres"]))
    # the centres lie among the tiny world's training boxes: inside the grid, at a box centre's height
    grid = dm.grid.range
    assert bool(((anchors[:, 0] >= grid[0]) & (anchors[:, 0] <= grid[3])).all())
    assert bool(((anchors[:, 2] > 0.0) & (anchors[:, 2] < 3.0)).all())
    # a user mistake is one line and exit code 2, nothing written
    bad = tmp_path / "bad.yaml"
    assert fit_anchors.main(["-c", "duocc/stream_agg", "data.preset=tiny", "--out", str(bad)]) == 2
    assert "has no DuOcc detector" in capsys.readouterr().err and not bad.exists()
