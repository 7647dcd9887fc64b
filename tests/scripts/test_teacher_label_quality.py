"""scripts/teacher_label_quality.py: a teacher's files scored against the frames' true labels."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from occplug.data.teacher_labels import write_teacher_file
from occplug.run import runner

ROOT = Path(__file__).resolve().parents[2]


def _run_with_teacher_files(tmp_path: Path, make) -> Path:
    """A run folder as a run of phases leaves it: ``teacher/config.yaml`` and ``pseudo_labels/<folder>/`` holding
    ``make(true_labels)`` for the first two training frames of the tiny world."""
    run = tmp_path / "run"
    (run / "teacher").mkdir(parents=True)
    (run / "teacher" / "config.yaml").write_text(
        f"base: [{ROOT / 'configs' / 'baseline.yaml'}]\ndata: {{preset: tiny}}\n"
    )
    folder = run / "pseudo_labels" / "teacher.occupancy.unlabelled"
    folder.mkdir(parents=True)
    (folder / "meta.json").write_text(json.dumps({"teacher": "teacher"}))
    dm, _ = runner.build_run(runner.load_config([str(run / "teacher" / "config.yaml")], []))
    dataset = dm.dataset("train")
    for i in range(2):
        frame = dataset[i]
        labels, confidence = make(frame.voxel_labels.numpy())
        write_teacher_file(folder, frame.token, labels, confidence)
    return run


def _score(script, run: Path, capsys) -> dict:
    script("teacher_label_quality").main([str(run), "--threshold", "0.7"])
    return json.loads(capsys.readouterr().out)


def test_true_labels_as_pseudo_labels_score_100(script, tmp_path, capsys):
    run = _run_with_teacher_files(tmp_path, lambda gt: (gt, np.ones(gt.shape)))
    out = _score(script, run, capsys)
    assert out["files_scored"] == 2
    assert out["mIoU"] == pytest.approx(100.0) and out["IoU_occupied"] == pytest.approx(100.0)
    assert out["share_at_or_above_0.7"] == pytest.approx(1.0)
    assert all(v == pytest.approx(100.0) for v in out["IoU_per_class"].values())


def test_all_free_below_the_threshold_scores_zero_and_keeps_nothing(script, tmp_path, capsys):
    run = _run_with_teacher_files(tmp_path, lambda gt: (np.full(gt.shape, 17), np.full(gt.shape, 0.5)))
    out = _score(script, run, capsys)
    assert out["mIoU"] == 0.0 and out["IoU_occupied"] == 0.0 and out["share_at_or_above_0.7"] == 0.0
    assert out["mIoU_at_or_above_0.7"] is None


def test_a_run_without_teacher_files_is_one_error_line(script, tmp_path):
    with pytest.raises(SystemExit, match="no pseudo_labels"):
        script("teacher_label_quality").main([str(tmp_path)])
