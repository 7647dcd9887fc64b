"""``python -m occplug_duocc.tools.stream_gain``: accuracy per position in the scene, on a tiny streamed DuOcc run."""

import pytest
import torch

from occplug.run import runner
from occplug_duocc.tools import stream_gain

SMALL = ["grid.range=[-8.0,-8.0,-1.0,8.0,8.0,5.4]", "model.encoder.out_channels=16", "model.encoder.width=16"]


def test_buckets_parse_and_a_bad_range_is_named():
    assert stream_gain.parse_buckets("0,1-2,3-") == [(0, 0), (1, 2), (3, 10**9)]
    with pytest.raises(ValueError, match="'3-1' has its end before its start"):
        stream_gain.parse_buckets("0,3-1")
    with pytest.raises(ValueError, match="'x' is not N, N-M or N-"):
        stream_gain.parse_buckets("0,x")


def test_buckets_add_up_to_validate_and_only_the_continuing_frames_feel_the_stream_cut(tmp_path):
    cfg = runner.load_config(["duocc/stream_agg_concat", "occplug/trainer/debug"], SMALL)
    run = tmp_path / "run"
    runner.fit(cfg, run)
    eval_set = ["data.frames_per_scene=3", "trainer.limit_val_batches=null"]
    buckets = [(0, 10**9), (0, 0), (1, 10**9)]
    _, (pooled, first, later), frames = stream_gain.confusions_by_position(run, eval_set, buckets)
    assert torch.equal(first + later, pooled) and pooled.sum() > 0
    ckpt = run / "checkpoints" / "last.ckpt"
    eval_cfg = runner.resolve_run_config([], eval_set, ckpt)
    val_scenes = runner.build_datamodule(eval_cfg).world_config.val_scenes
    assert frames == [3 * val_scenes, val_scenes, 2 * val_scenes]
    # the pooled bucket is what occplug validate reports
    reference = runner.evaluate(eval_cfg, ckpt).results
    results = stream_gain.results_by_position(run, eval_set, buckets)
    for key in stream_gain.KEYS:
        assert results[0][key] == pytest.approx(reference[key], abs=1e-4), key
    assert results[0]["frames"] == 3 * val_scenes
    # cutting the stream at every frame changes nothing at the scene starts, and the later frames' predictions
    _, (cut_first, cut_later), _ = stream_gain.confusions_by_position(
        run, [*eval_set, "model.scene.max_gap_s=0.01"], [(0, 0), (1, 10**9)]
    )
    assert torch.equal(cut_first, first) and not torch.equal(cut_later, later)
