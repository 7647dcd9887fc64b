"""occplug_duocc.tools.selection: what QueryAgg's selection hands DQA, on hand-made frames and on the tiny world."""

import pytest
import torch

from occplug_duocc.tools.selection import SelectionTally, main, near_a_box, stream_selection_report


def test_near_a_box_is_an_xy_radius_both_ways():
    centres = torch.tensor([[0.0, 0.0], [5.0, 5.0], [10.6, 0.0]])
    boxes = torch.tensor([[0.5, 0.5, 9.0], [10.0, 0.0, -9.0], [-20.0, 0.0, 0.0]])  # z plays no part
    real, found = near_a_box(centres, boxes, 1.0)
    assert real.tolist() == [True, False, True] and found.tolist() == [True, True, False]
    assert near_a_box(centres[:0], boxes, 1.0)[1].tolist() == [False, False, False]


def test_the_tally_gives_the_known_counts():
    tally = SelectionTally([0.2, 0.5])
    scores = torch.tensor([0.9, 0.4, 0.3, 0.1])
    centres = torch.tensor([[0.0, 0.0], [30.0, 0.0], [4.0, 0.0], [4.2, 0.0]])  # the first and the last two are real
    gt = torch.tensor([[0.3, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0], [4.0, 0.3, 0.0, 1.0, 1.0, 1.7, 0.0]])
    selected = torch.tensor([True, True, False, False])
    tally.add(scores, centres, gt, selected, torch.tensor([3, 4, 4, 9]), torch.tensor([4, 5, 9]), 1.0)
    tally.add(scores[:0], centres[:0], gt[:0], selected[:0], None, None, 1.0)  # a frame with nothing
    r = tally.report()
    assert r["frames"] == 2 and r["true_boxes_per_frame"] == 1.0
    assert r["nearest_query_to_a_true_box_m"] == pytest.approx((0.3 + 0.3) / 2)  # (0.3, 0) to (0, 0); (4, .3) to (4, 0)
    # > 0.2: queries 0, 1, 2 (0 and 2 real; both boxes found); > 0.5: query 0 only (one box found)
    assert r["by_score_threshold"]["0.2"] == {"queries_per_frame": 1.5, "precision_pct": 66.67, "recall_pct": 100.0}
    assert r["by_score_threshold"]["0.5"] == {"queries_per_frame": 0.5, "precision_pct": 100.0, "recall_pct": 50.0}
    # DQA wrote voxels 3, 4, 9 (4 twice): 4 and 9 lie in a true box
    assert r["model_selection"] == {
        "queries_per_frame": 1.0,
        "precision_pct": 50.0,
        "voxels_written_per_frame": 1.5,
        "written_inside_a_true_box_pct": 66.67,
    }


def test_the_model_selects_at_evaluation_what_its_score_threshold_takes(model_dm):
    model, dm = model_dm
    data = dm.dataset("val")
    batches = [dm.collate([data[i]]) for i in range(len(data))]
    threshold = model.scene.query_agg.score_threshold
    report = stream_selection_report(model, batches, thresholds=[0.0, threshold, 1.0])
    by = report["by_score_threshold"]
    assert report["frames"] == len(data)
    queries = model.scene.query_agg.detector.num_queries
    assert by["0"]["queries_per_frame"] == queries and by["1"]["queries_per_frame"] == 0.0
    assert report["model_selection"]["queries_per_frame"] == by[f"{threshold:g}"]["queries_per_frame"]


def test_a_bad_radius_is_one_line_and_exit_2(tmp_path, capsys):
    assert main([str(tmp_path / "missing.ckpt"), "--radius", "0"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "--radius" in err and len(err.strip().splitlines()) == 1
