"""scripts/stream_gain_by_frame.py: accuracy per position in the scene, on a tiny streamed DuOcc run."""

import importlib.util
from pathlib import Path

import pytest

from occplug import runner

ROOT = Path(__file__).resolve().parents[3]
SMALL = ["grid.range=[-8.0,-8.0,-1.0,8.0,8.0,5.4]", "model.encoder.out_channels=16", "model.encoder.width=16"]


def _script():
    spec = importlib.util.spec_from_file_location("stream_gain_by_frame", ROOT / "scripts" / "stream_gain_by_frame.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_buckets_parse_and_a_reversed_range_is_named():
    script = _script()
    assert script.parse_buckets("0,1-2,3-") == [(0, 0), (1, 2), (3, 10**9)]
    with pytest.raises(SystemExit, match="'3-1' has its end before its start"):
        script.parse_buckets("0,3-1")


def test_all_positions_pooled_equal_validate_and_the_reset_frames_ignore_the_stream_cut(tmp_path):
    script = _script()
    cfg = runner.load_config(["duocc/stream_agg_concat", "occplug/trainer/debug"], SMALL)
    run = tmp_path / "run"
    runner.fit(cfg, run)
    eval_set = ["data.frames_per_scene=3", "trainer.limit_val_batches=null"]
    buckets = [(0, 10**9), (0, 0), (1, 10**9)]
    pooled, first, later = script.results_by_position(run, eval_set, buckets)
    ckpt = run / "checkpoints" / "last.ckpt"
    eval_cfg = runner.resolve_run_config([], eval_set, ckpt)
    reference = runner.evaluate(eval_cfg, ckpt).results
    val_scenes = runner.build_datamodule(eval_cfg).world_config.val_scenes
    assert (pooled["frames"], first["frames"], later["frames"]) == (3 * val_scenes, val_scenes, 2 * val_scenes)
    for key in script.KEYS:
        assert pooled[key] == pytest.approx(reference[key], abs=1e-4), key
    # cutting the stream at every frame changes nothing where the stream starts anyway
    (cut_first,) = script.results_by_position(run, [*eval_set, "model.scene.max_gap_s=0.01"], [(0, 0)])
    assert {k: cut_first[k] for k in script.KEYS} == {k: first[k] for k in script.KEYS}
