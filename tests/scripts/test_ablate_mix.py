"""scripts/ablate_mix.py: every mix beside its parents, per seed, with a fake fit (the real runs are the script's)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from occplug.config import phase_specs
from occplug.run import runner


def _fake_metrics(config: str, overrides: list[str]) -> dict:
    """Numbers that depend on the run (its config, seed and overrides), so a table cell shows which run it came from."""
    seed = int(next(o for o in overrides if o.startswith("seed="))[5:])
    base = 10.0 * (1 + sum(map(ord, config + " ".join(overrides))) % 7) + seed
    return {"mIoU": base, "IoU": base + 40, "RayIoU": base / 2, "RayIoU_geometry": base + 1, "mIoU_dynamic": 0.0}


def test_every_mix_is_measured_beside_its_parents_per_seed(script, tmp_path, monkeypatch, capsys):
    ablate = script("ablate_mix")
    calls: list[tuple[str, list[str], Path]] = []

    def fake_fit(config, overrides, out, label):
        calls.append((config, list(overrides), out))
        out.mkdir(parents=True)
        metrics = _fake_metrics(config, list(overrides))
        if any(o.startswith("phases.") for o in overrides):  # a phased run's summary names its final phase
            metrics = {**metrics, "final_phase": "finetune", "phases": {"teacher": {}, "student": {}, "finetune": {}}}
        (out / "metrics.json").write_text(json.dumps(metrics))
        return out

    monkeypatch.setattr(ablate, "fit_in_process", fake_fit)
    args = ["--seeds", "0", "1", "--epochs", "0.5", "--out", str(tmp_path / "abl"), "--results", str(tmp_path / "res")]
    args += ["--set", "data.batch_size=1", "phases.student.trainer.max_epochs=2"]
    ablate.main(args)
    printed = capsys.readouterr().out
    # each row trains once per seed, also the rows two mixes share (B at 100 % and at 10 %)
    assert sorted(out.name for _, _, out in calls) == sorted(f"{r}-seed{s}" for r in ablate.ROWS for s in (0, 1))
    by_run = {out.name: (config, overrides) for config, overrides, out in calls}
    # the parents' budgets, halved: QueryOcc 4 -> 2 epochs, DuOcc 8 -> 4; the phased row per phase (8, 8, 4 -> 4, 4, 2)
    assert "trainer.max_epochs=2" in by_run["queryocc_base-seed0"][1]
    assert "trainer.max_epochs=2" in by_run["label_free_stream_t0-seed1"][1]
    assert "trainer.max_epochs=4" in by_run["duocc_b_10pct-seed0"][1]
    assert "trainer.max_epochs=10" in by_run["duocc_b_10pct_20ep-seed0"][1]
    phased = by_run["duocc_b_three_phase_10pct-seed1"][1]
    assert [o for o in phased if o.startswith("phases.")] == [
        "phases.teacher.trainer.max_epochs=4",
        "phases.student.trainer.max_epochs=4",
        "phases.finetune.trainer.max_epochs=2",
        "phases.student.trainer.max_epochs=2",  # --set, after the budget: it wins
    ]
    assert all("data.batch_size=1" in o for _, o in by_run.values())
    assert not any(x.startswith("phases.") for x in by_run["duocc_b_10pct-seed0"][1])  # no phase to set
    assert "data.label_fraction=0.1" in by_run["duocc_b_10pct-seed1"][1]
    assert "data.label_fraction=0.1" not in by_run["duocc_b_100pct-seed1"][1]
    # one table per mix in its parents' columns, mean ± std over the two seeds of exactly that row's runs
    for title in ablate.MIXES:
        assert f"### {title}" in printed
    assert "| Sem.RayIoU | Occ.RayIoU | Sem.IoU | Occ.IoU |" in printed
    assert printed.count("| mIoU | mIoU_D | mIoU_S | IoU |") == 2
    for name, key in (
        ("queryocc_base", "RayIoU"),
        ("label_free_stream", "RayIoU"),
        ("duocc_b_three_phase_10pct", "mIoU"),
    ):
        seeds = [_fake_metrics(*by_run[f"{name}-seed{s}"])[key] for s in (0, 1)]
        expected = ablate.mean_std(seeds)
        assert any(
            line.startswith(f"| {ablate.ROWS[name].label} | `{name}` | {expected} |") for line in printed.splitlines()
        )
    assert "label_free_stream - queryocc_base (Sem.RayIoU):" in printed
    assert "label_free_stream_t0 - label_free_stream (Sem.RayIoU):" in printed
    assert "label_free_stream - label_free_stream_t0" not in printed  # each pair once
    assert "duocc_b_three_phase_10pct - duocc_b_10pct (mIoU):" in printed
    # per-seed JSONs: one per row and seed, the row's own values and the exact overrides it ran with
    for config, overrides, out in calls:
        row, seed = out.name.rsplit("-seed", 1)
        record = json.loads((tmp_path / "res" / f"{row}-seed{seed}.json").read_text())
        iou = record["values"].get("IoU", record["values"].get("Occ.IoU"))  # DuOcc's column name, QueryOcc's
        assert iou == _fake_metrics(config, overrides)["IoU"]
        assert record["settings"]["overrides"] == overrides and record["settings"]["config"] == config
    # a second run reuses every finished run directory: nothing trains
    calls.clear()
    ablate.main(args)
    assert calls == []


def test_every_planned_run_composes_and_validates(script):
    """The overrides the script adds (budgets, label fraction, phase epochs) are valid for each row's config."""
    ablate = script("ablate_mix")
    args = ablate.argparse.Namespace(preset="tiny", epochs=1.0, set=["phases.student.trainer.max_epochs=2"])
    for name, row in ablate.ROWS.items():
        cfg = runner.load_config([row.config], ablate.overrides(name, 0, args))
        if row.epochs is None:
            assert [s.config["trainer"]["max_epochs"] for s in phase_specs(cfg)] == [8, 2, 4]
        else:
            assert cfg["trainer"]["max_epochs"] == row.epochs


def test_a_finished_run_of_other_settings_is_refused_not_reused(script, tmp_path, monkeypatch, capsys):
    ablate = script("ablate_mix")

    def fake_fit(config, overrides, out, label):
        out.mkdir(parents=True)
        (out / "metrics.json").write_text(json.dumps(_fake_metrics(config, list(overrides))))
        return out

    monkeypatch.setattr(ablate, "fit_in_process", fake_fit)
    common = ["--rows", "queryocc_base", "--seeds", "0", "--out", str(tmp_path / "abl")]
    ablate.main([*common, "--epochs", "0.5"])
    ablate.main([*common, "--epochs", "0.5"])  # the same settings: the finished run is reused
    capsys.readouterr()
    with pytest.raises(SystemExit) as stop:
        ablate.main([*common, "--epochs", "1"])  # another budget: never the old numbers
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "queryocc_base-seed0" in err[0]
