"""``occplug data stats``: voxels per class equal a direct count of the frames' labels; user mistakes exit 2."""

from pathlib import Path

import numpy as np
import pytest
import torch

from occplug.cli import main
from occplug.data.stats import class_counts
from occplug.run import runner

BASELINE = str(Path(__file__).resolve().parents[2] / "configs" / "baseline.yaml")
TINY = ["data.preset=tiny"]


def _printed_counts(out: str) -> list[int]:
    line = next(ln for ln in out.splitlines() if ln.startswith("class_frequencies: "))
    return [int(v) for v in line.split("[", 1)[1].rstrip("]").split(",")]


def test_stats_equal_a_direct_count_of_the_labels(capsys):
    assert main(["data", "stats", "-c", BASELINE, *TINY]) == 0
    counts = _printed_counts(capsys.readouterr().out)
    dm = runner.build_datamodule(runner.load_config([BASELINE], TINY))
    frames = dm.dataset("train")
    direct = sum(np.bincount(frames[i].voxel_labels.numpy().ravel(), minlength=18) for i in range(len(frames)))
    assert counts == direct.tolist() and sum(counts) == len(frames) * frames[0].voxel_labels.numel()


def test_camera_mask_counts_only_visible_voxels_and_unlabelled_frames_are_skipped(capsys):
    dm = runner.build_datamodule(runner.load_config([BASELINE], TINY))
    frames = dm.dataset("train")
    whole = class_counts(frames, 18)
    seen = class_counts(frames, 18, mask="camera")
    visible = sum(int(frames[i].mask_camera.sum()) for i in range(len(frames)))
    assert int(seen.counts.sum()) == visible < int(whole.counts.sum()) and bool((seen.counts <= whole.counts).all())
    assert main(["data", "stats", "-c", BASELINE, *TINY, "data.label_fraction=0.5"]) == 0
    out = capsys.readouterr().out
    labelled = sum(bool(f.has_voxel_labels) for f in runner.build_datamodule(
        runner.load_config([BASELINE], [*TINY, "data.label_fraction=0.5"])).dataset("train"))
    assert 0 < labelled < len(frames) and f"{labelled} frames ({len(frames) - labelled} without" in out
    assert sum(_printed_counts(out)) == labelled * frames[0].voxel_labels.numel()


def test_class_counts_ignore_ids_beyond_the_classes():
    class F:
        voxel_labels = torch.tensor([[0, 1], [255, 1]], dtype=torch.uint8)
        mask_camera = None
        has_voxel_labels = True

    result = class_counts([F()], 3)
    assert result.counts.tolist() == [1, 2, 0] and result.frames == 1 and result.skipped == 0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--split", "bogus"], "--split: expected train, val or test"),
        (["--max-frames", "0"], "--max-frames: expected a positive number"),
        (["data.bogus_knob=1"], "bogus_knob"),
    ],
)
def test_user_mistakes_exit_2_with_one_line(args, message, capsys):
    assert main(["data", "stats", "-c", BASELINE, *TINY, *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
