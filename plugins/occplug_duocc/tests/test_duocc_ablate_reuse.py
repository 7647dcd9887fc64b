"""``occplug_duocc.tools.ablate`` reuses a finished run only when it is of the config the recipe composes today.

A run directory's ``config.yaml`` holds every component argument with its default, so the comparison is against
``runner.saved_run_config`` of today's composition (it compared with the bare composition, and so refused every
finished run)."""

from __future__ import annotations

import argparse
import json

import pytest
import yaml

from occplug.run import runner
from occplug_duocc.tools import ablate


def _finished_run(tmp_path, cfg):
    out = tmp_path / "full_gt_trained-seed0"
    out.mkdir()
    (out / "config.yaml").write_text(yaml.safe_dump(runner.saved_run_config(cfg)))
    (out / "metrics.json").write_text(json.dumps({"mIoU": 1.0}))
    return out


def test_a_finished_run_of_today_s_recipe_is_reused_and_another_is_refused(tmp_path, capsys):
    args = argparse.Namespace(out=str(tmp_path), preset="tiny", epochs=1, set=[])
    overrides = ["seed=0", "trainer.enable_progress_bar=false", "data.preset=tiny", "trainer.max_epochs=1"]
    cfg = runner.load_config(["duocc/full_gt_trained"], overrides)
    out = _finished_run(tmp_path, cfg)
    assert ablate.fit("full_gt_trained", 0, args) == out  # reused: nothing trained
    changed = runner.saved_run_config(cfg)
    changed["model"]["scene"]["query_agg"]["score_threshold"] = 0.5
    (out / "config.yaml").write_text(yaml.safe_dump(changed))
    with pytest.raises(SystemExit) as stop:
        ablate.fit("full_gt_trained", 0, args)
    assert stop.value.code == 2
    assert "was trained with another config than duocc/full_gt_trained" in capsys.readouterr().err
