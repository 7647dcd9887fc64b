"""``occplug bench``: one row per model, recorded accuracy as written, interleaved rounds, clean errors."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import pytest
import yaml

from occplug.cli import main
from occplug.run import runner
from occplug.run.bench import BenchReport, BenchRow, Spread, Target, interleave, make_row, mean_std, read_accuracy

ROOT = Path(__file__).resolve().parents[2]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
METRICS = {"mIoU": 12.5, "IoU": 40.25, "RayIoU": 9.75, "IoU_car": 3.0, "eval_mask": "camera", "global_step": 2}
COLUMNS = [
    "model", "source", "params", "latency_ms", "memory_mib", "train_step_ms", "train_memory_mib",
    "mIoU", "IoU", "RayIoU", "eval_mask", "latency_min_ms", "latency_max_ms", "train_step_min_ms",
    "train_step_max_ms",
]  # fmt: skip


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    """``occplug bench --json`` on a run directory (its metrics.json written here) and a config, both tiny."""
    tmp = tmp_path_factory.mktemp("bench")
    run = tmp / "myrun"
    run.mkdir()
    cfg = runner.load_config([BASELINE], ["data.preset=tiny"])
    (run / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    (run / "metrics.json").write_text(json.dumps(METRICS))
    out = tmp / "bench.json"
    code = main(
        ["bench", str(run), BASELINE, "--preset", "tiny", "--device", "cpu", "--repeats", "2", "--warmup", "1",
         "--train-repeats", "1", "--json", "-o", str(out)]
    )  # fmt: skip
    assert code == 0
    return BenchReport.from_json(out.read_text()), cfg


def test_one_row_per_model_with_every_column(measured):
    report, cfg = measured
    assert [r.model for r in report.rows] == ["myrun", "baseline"]
    assert report.settings == {
        "repeats": 2, "warmup": 1, "train_repeats": 1, "batch_size": 1, "preset": "tiny",
    }  # fmt: skip
    assert report.device.startswith("cpu") and "torch" in report.versions and "lightning" in report.versions
    # both rows are the same architecture: the same parameter count, the baseline's own
    dm, model = runner.build_run(cfg)
    assert [r.params for r in report.rows] == [sum(p.numel() for p in model.parameters())] * 2
    for r in report.rows:
        assert 0 < r.latency_min_ms <= r.latency_ms <= r.latency_max_ms
        assert r.train_step_ms > 0 and r.train_step_min_ms == r.train_step_ms == r.train_step_max_ms  # one repeat
        assert r.memory_mib > 50 and r.train_memory_mib >= r.memory_mib  # peak RSS only grows
    markdown = report.to_markdown().splitlines()
    assert markdown[0].startswith("machine: ") and markdown[1].startswith("device: cpu")
    assert markdown[2].startswith("versions: python ")
    table = [line for line in markdown if line.startswith("|")]
    assert len(table) == 2 + 2  # header, rule, one row per model
    assert [c.strip() for c in table[0].strip("|").split("|")] == [
        "model", "params", "latency (ms/frame)", "memory (MiB)", "train step (ms)", "train memory (MiB)",
        "mIoU", "IoU", "RayIoU", "eval mask",
    ]  # fmt: skip
    assert all(len(line.strip("|").split("|")) == 10 for line in table)


def test_accuracy_is_what_the_run_recorded_and_a_config_has_none(measured):
    report, _ = measured
    run, config = report.rows
    assert (run.mIoU, run.IoU, run.RayIoU, run.eval_mask) == (12.5, 40.25, 9.75, "camera")
    assert (config.mIoU, config.IoU, config.RayIoU, config.eval_mask) == (None, None, None, None)
    cells = [c.strip() for c in report.to_markdown().splitlines()[-1].strip("|").split("|")]
    assert cells[0] == "baseline" and cells[6:] == ["—"] * 4
    cells = [c.strip() for c in report.to_markdown().splitlines()[-2].strip("|").split("|")]
    assert cells[6:] == ["12.50", "40.25", "9.75", "camera"]


def test_json_and_csv_round_trip(measured):
    report, _ = measured
    assert BenchReport.from_json(report.to_json()) == report
    text = report.to_csv()
    assert BenchReport.from_csv(text) == report
    rows = list(csv.DictReader(line for line in io.StringIO(text) if not line.startswith("#")))
    assert list(rows[0]) == COLUMNS and len(rows) == 2
    assert rows[1]["mIoU"] == "—" and float(rows[0]["IoU"]) == 40.25


def test_read_accuracy_takes_a_prefixed_key_and_leaves_missing_ones_empty():
    found = read_accuracy({"occ3d_miou/mIoU": 7.0, "ssc/mIoU": 3.0, "IoU": 1.5, "eval_mask": "lidar"})
    assert found == {"mIoU": 7.0, "IoU": 1.5, "RayIoU": None, "eval_mask": "lidar"}


def test_rounds_are_interleaved_and_alternate_order():
    calls: list[tuple[str, int]] = []

    class Fake:
        def __init__(self, name: str) -> None:
            self.name, self.n = name, 0

        def request(self, command: str) -> dict:
            calls.append((self.name, self.n))
            self.n += 1
            return {"ms": 10.0 * self.n + (1 if self.name == "b" else 0)}

    out = interleave([Fake("a"), Fake("b")], "latency", 3)
    assert calls == [("a", 0), ("b", 0), ("b", 1), ("a", 1), ("a", 2), ("b", 2)]
    assert out == [[10.0, 20.0, 30.0], [11.0, 21.0, 31.0]]


class FakeClock:
    """A timer that advances only when told: each model's repeats take the given milliseconds."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_the_row_summarises_each_models_repeats_as_min_median_max():
    clock = FakeClock()
    durations = {"a": iter([30.0, 10.0, 20.0, 50.0, 40.0]), "b": iter([5.0, 7.0, 6.0, 9.0, 8.0])}

    class Timed:
        def __init__(self, name: str) -> None:
            self.name = name

        def request(self, command: str) -> dict:  # a worker timing one repeat with the clock
            start = clock()
            clock.now += next(durations[self.name]) / 1000.0
            return {"ms": (clock() - start) * 1000.0}

    workers = [Timed("a"), Timed("b")]
    latency = interleave(workers, "latency", 3)
    train = interleave(workers, "train", 2)
    targets = [Target(n, f"{n}.yaml", "config", {}) for n in "ab"]
    stats = {"memory": 2**20 * 100, "train_memory": 2**20 * 300}
    rows = [make_row(t, {"params": 7}, lat, tr, stats) for t, lat, tr in zip(targets, latency, train, strict=True)]
    spread = [(r.latency_min_ms, r.latency_ms, r.latency_max_ms) for r in rows]
    assert spread == [pytest.approx((10.0, 20.0, 30.0)), pytest.approx((5.0, 6.0, 7.0))]
    steps = [(r.train_step_min_ms, r.train_step_ms, r.train_step_max_ms) for r in rows]
    assert steps == [pytest.approx((40.0, 45.0, 50.0)), pytest.approx((8.0, 8.5, 9.0))]  # even count: mean of two
    assert (rows[0].memory_mib, rows[0].train_memory_mib) == (100.0, 300.0)
    report = BenchReport("host", "cpu", {}, {"repeats": 3, "warmup": 0, "train_repeats": 2, "batch_size": 1}, rows)
    assert report.to_markdown().splitlines()[-2] == (
        "| a | 7 | 20.00 (10.00–30.00) | 100 | 45.0 (40.0–50.0) | 300 | — | — | — | — |"
    )
    assert BenchReport.from_csv(report.to_csv()) == report
    inference_only = make_row(targets[0], {"params": 7}, [3.0], [], stats)
    assert inference_only.train_step_ms is None and inference_only.train_step_min_ms is None
    assert Spread.of([2.0, 1.0]) == Spread(1.0, 1.5, 2.0)
    with pytest.raises(ValueError):
        Spread.of([])


def test_markdown_of_a_known_report():
    row = BenchRow("m", "cfg.yaml", 1_234_567, 12.345, 100.4, 56.78, 200.6)
    report = BenchReport(
        "host: cpu", "cpu (2 torch threads)", {"torch": "2"},
        {"repeats": 5, "warmup": 1, "train_repeats": 2, "batch_size": 1, "preset": None}, [row],
    )  # fmt: skip
    assert report.to_markdown().splitlines()[-1] == "| m | 1.23 M | 12.35 | 100 | 56.8 | 201 | — | — | — | — |"


@pytest.mark.parametrize("case", ["missing", "no_run_dir", "missing_yaml", "bad_repeats", "bad_train_repeats"])
def test_bad_inputs_are_one_error_line_exit_2(case, tmp_path, capsys):
    folder = tmp_path / "folder"
    folder.mkdir()
    (folder / "notes.txt").write_text("not a run")
    args = {
        "missing": ["bench", str(tmp_path / "nope")],
        "no_run_dir": ["bench", str(folder)],
        "missing_yaml": ["bench", str(tmp_path / "nope.yaml")],
        "bad_repeats": ["bench", BASELINE, "--repeats", "0"],
        "bad_train_repeats": ["bench", BASELINE, "--train-repeats", "-1"],
    }[case]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("error: ")
    expected = {
        "missing": f"{tmp_path / 'nope'}: no such run directory or config file",
        "no_run_dir": f"{folder}: a folder but not an occplug run directory (no config.yaml)",
        "missing_yaml": f"{tmp_path / 'nope.yaml'}: no such run directory or config file",
        "bad_repeats": "--repeats: expected an int >= 1, got 0",
        "bad_train_repeats": "--train-repeats: expected an int >= 0 (0: inference only), got -1",
    }[case]
    assert err == f"error: {expected}"


def test_out_is_checked_before_measuring_and_written_whole(tmp_path, monkeypatch, capsys):
    """``-o`` below a file stops before any model is built; a good one is replaced atomically."""
    import occplug.run.bench as bench

    row = BenchRow("m", "cfg.yaml", 1_234_567, 12.345, 100.4, 56.78, 200.6)
    report = BenchReport(
        "host: cpu", "cpu (2 torch threads)", {"torch": "2"},
        {"repeats": 5, "warmup": 1, "train_repeats": 2, "batch_size": 1, "preset": None}, [row],
    )  # fmt: skip
    resolved: list[str] = []
    monkeypatch.setattr(bench, "resolve_target", lambda ref, settings: resolved.append(ref) or ref)
    monkeypatch.setattr(bench, "run_bench", lambda targets, settings, progress=None: report)
    (tmp_path / "a_file").write_text("x\n")
    below = tmp_path / "a_file" / "table.md"
    assert main(["bench", BASELINE, "-o", str(below)]) == 2
    assert capsys.readouterr().err.strip() == f"error: --out {below}: {below.parent} is a file, not a folder"
    assert resolved == []  # nothing built, nothing measured
    out = tmp_path / "table.md"
    out.write_text("an older, longer table\n" * 50)
    written = []
    atomic = runner.write_text_atomic
    monkeypatch.setattr(runner, "write_text_atomic", lambda path, text: (written.append(path), atomic(path, text)))
    assert main(["bench", BASELINE, "-o", str(out)]) == 0
    assert written == [out] and out.read_text() == report.to_markdown()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "table.md"]  # no temporary file left


def test_training_rounds_generate_only_the_frames_they_read(tmp_path, monkeypatch):
    """The training rounds fit a few steps: they must not pregenerate the whole synthetic split (an occ3d world
    takes hours), only the frames those steps read."""
    from lightning.pytorch.callbacks import Callback

    from occplug.run.bench import _train

    monkeypatch.setenv("OCCPLUG_CACHE", str(tmp_path))
    cfg = runner.load_config([BASELINE], ["data.preset=tiny", "data.batch_size=1"])
    dm, model = runner.build_run(cfg)
    steps = []

    class Count(Callback):
        def on_train_batch_end(self, *args):
            steps.append(1)

    _train(cfg, dm, model, {"device": "cpu", "warmup": 1, "train_repeats": 1}, Count())
    cached = list(tmp_path.rglob("*.pt"))
    assert len(steps) == 2
    assert 1 <= len(cached) <= 3  # 2 steps at batch 1 (+ one batch Lightning reads ahead); train + val hold 8


def test_train_repeats_0_measures_inference_only(tmp_path):
    out = tmp_path / "bench.json"
    args = ["bench", BASELINE, "--preset", "tiny", "--device", "cpu", "--repeats", "1", "--warmup", "0"]
    assert main([*args, "--train-repeats", "0", "--json", "-o", str(out)]) == 0
    report = BenchReport.from_json(out.read_text())
    (row,) = report.rows
    assert row.latency_ms > 0 and row.memory_mib > 0
    assert row.train_step_ms is None and row.train_memory_mib is None
    assert BenchReport.from_csv(report.to_csv()) == report
    assert report.to_markdown().splitlines()[-1].split(" | ")[4:6] == ["—", "—"]


def test_mean_std_is_the_sample_std_over_the_finite_values():
    assert mean_std([1.0, 2.0, 3.0]) == "2.00 ± 1.00"
    assert mean_std([1.0, float("nan"), 3.0]) == "2.00 ± 1.41"  # NaN left out
    assert mean_std([2.5]) == "2.50" and mean_std([2.5, float("nan")]) == "2.50"
    assert mean_std([]) == "—" and mean_std([float("nan")], empty="-") == "-"
