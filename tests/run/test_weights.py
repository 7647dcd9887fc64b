"""Initialising a model from a state-dict file with a key map (top-level ``init_from``; occplug.run.weights)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

from occplug.cli import main
from occplug.config import ConfigError
from occplug.config.phases import parse_init_from, phase_specs
from occplug.run import runner
from occplug.run.weights import init_from_config

ROOT = Path(__file__).resolve().parents[2]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
TINY = ["data.preset=tiny", "data.num_workers=0", "trainer.accelerator=cpu", "trainer.enable_progress_bar=false"]
MAP = "{img_backbone.: model.encoder.}"


def _build(seed, *overrides):
    torch.manual_seed(seed)
    cfg = runner.load_config([BASELINE], [*TINY, *overrides])
    return cfg, runner.build_run(cfg)[1]


@pytest.fixture(scope="module")
def donor():
    """The state dict of another model's encoder, named as an mmdet detector checkpoint names its backbone."""
    _, model = _build(1)
    return {
        k.replace("encoder.", "img_backbone.", 1): v for k, v in model.state_dict().items() if k.startswith("encoder.")
    }


def _save(path, state, nest="state_dict"):
    extra = {  # a detector's other parts: reported, never loaded
        "img_neck.lateral.weight": torch.randn(8, 4, 1, 1),
        "pts_bbox_head.cls.weight": torch.randn(10, 8),
        "pts_bbox_head.cls.bias": torch.randn(10),
    }
    payload = {**state, **extra}
    torch.save({nest: payload, "meta": {"epoch": 24}} if nest else payload, path)
    return str(path)


def _init(path, *entry_overrides, seed=3, **kw):
    entry = ", ".join(f"{k}: {v}" for k, v in {"file": path, "map": MAP, **kw}.items())
    cfg, model = _build(seed, f"init_from=[{{{entry}}}]", *entry_overrides)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    return model, before, init_from_config(model, cfg)


@pytest.mark.parametrize("nest", ["state_dict", "model", None])
def test_mapped_tensors_land_and_the_rest_stays(tmp_path, donor, nest):
    path = _save(tmp_path / "bevdet.pth", donor, nest)
    model, before, lines = _init(path, strict="true")
    after = model.state_dict()
    for key, value in after.items():
        if key.startswith("encoder."):
            assert torch.equal(value, donor["img_backbone." + key[len("encoder.") :]]), key
        else:
            assert torch.equal(value, before[key]), key
    assert not torch.equal(after["encoder.body.0.0.weight"], before["encoder.body.0.0.weight"])  # a real change
    n = len(donor)
    assert lines == [
        f"init_from[0]: {path}: loaded {n} tensors; missing 0; unexpected 3 "
        "(3 not mapped, 0 mapped to null, 0 not in the model)"
    ]


def test_longest_prefix_first_null_drops_and_strict_counts_what_is_left(tmp_path, donor):
    path = _save(tmp_path / "bevdet.pth", donor)
    skip = "{img_backbone.: model.encoder., img_backbone.body.2.: null}"  # written shortest first: order is by length
    model, before, lines = _init(path, map=skip, strict="false")
    dropped = [k for k in donor if k.startswith("img_backbone.body.2.")]
    assert dropped
    for key, value in model.state_dict().items():
        source = "img_backbone." + key[len("encoder.") :]
        expected = donor[source] if key.startswith("encoder.") and source not in dropped else before[key]
        assert torch.equal(value, expected), key
    assert lines == [
        f"init_from[0]: {path}: loaded {len(donor) - len(dropped)} tensors; missing {len(dropped)}; unexpected "
        f"{3 + len(dropped)} (3 not mapped, {len(dropped)} mapped to null, 0 not in the model)"
    ]
    with pytest.raises(runner.RunError, match=r"gives no tensor for model\.encoder\.body\.2\..* strict"):
        _init(path, map=skip, strict="true")


def test_a_classifier_head_in_the_file_is_an_error_when_strict_unless_mapped_to_null(tmp_path, donor):
    path = _save(tmp_path / "imagenet.pth", {**donor, "img_backbone.fc.weight": torch.randn(1000, 64)})
    with pytest.raises(
        runner.RunError,
        match=r"^init_from\[0\]: .*imagenet.pth: img_backbone.fc.weight maps to model.encoder.fc.weight, which the "
        r"model does not have \(1 such keys; strict",
    ):
        _init(path)
    _, _, lines = _init(path, map="{img_backbone.: model.encoder., img_backbone.fc.: null}")
    assert lines[0].endswith("unexpected 4 (3 not mapped, 1 mapped to null, 0 not in the model)")
    _, _, lines = _init(path, strict="false")
    assert lines[0].endswith("unexpected 4 (3 not mapped, 0 mapped to null, 1 not in the model)")


def test_an_occplug_checkpoint_loads_without_a_map(tmp_path):
    _, source = _build(1)
    path = tmp_path / "last.ckpt"
    torch.save({"state_dict": source.state_dict(), "epoch": 3}, path)
    cfg, model = _build(3, f"init_from=[{{file: {path}}}]")
    init_from_config(model, cfg)
    assert all(torch.equal(v, source.state_dict()[k]) for k, v in model.state_dict().items())


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("missing", r"init_from\[0\]\.file: .*nope\.pth does not exist"),
        ("garbage", r"init_from\[0\]\.file: .*garbage\.pth cannot be read as a state dict \(torch\.load, weights_only"),
        (
            "maps_nothing",
            r"init_from\[0\]\.map: no key of .*bevdet\.pth starts with 'backbone\.' \(its keys start with: "
            r"img_backbone\., img_neck\., pts_bbox_head\.\)",
        ),
        (
            "lands_nowhere",
            r"init_from\[0\]\.map: the \d+ keys of .*bevdet\.pth under 'img_backbone\.' map onto nothing in the model "
            r"\(e\.g\. img_backbone\.body\.0\.0\.weight -> model\.encodr\.body\.0\.0\.weight",
        ),
        (
            "shape",
            r"init_from\[0\]: .*bevdet\.pth: img_backbone\.body\.0\.0\.weight is \(32, 3, 1, 1\) but "
            r"model\.encoder\.body\.0\.0\.weight is \(32, 3, 3, 3\)",
        ),
    ],
)
def test_fit_stops_with_one_line_and_exit_code_2_writing_nothing(tmp_path, donor, capsys, case, message):
    good = _save(tmp_path / "bevdet.pth", donor)
    entry = {
        "missing": f"{{file: {tmp_path / 'nope.pth'}}}",
        "garbage": f"{{file: {tmp_path / 'garbage.pth'}}}",
        "maps_nothing": f"{{file: {good}, map: {{backbone.: model.encoder.}}}}",
        "lands_nowhere": f"{{file: {good}, map: {{img_backbone.: model.encodr.}}}}",
        "shape": f"{{file: {tmp_path / 'bevdet.pth'}, map: {MAP}}}",
    }[case]
    (tmp_path / "garbage.pth").write_text("not a checkpoint")
    if case == "shape":
        _save(tmp_path / "bevdet.pth", {**donor, "img_backbone.body.0.0.weight": torch.zeros(32, 3, 1, 1)})
    run_dir = tmp_path / "run"
    code = main(["fit", "-c", BASELINE, *TINY, f"init_from=[{entry}]", "--run-dir", str(run_dir)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert err.startswith("error: ") and re.search(message, err), err
    assert not run_dir.exists() or not any(run_dir.iterdir())


def test_fit_loads_before_training_and_resume_does_not_reload(tmp_path, donor, capsys):
    path = _save(tmp_path / "bevdet.pth", donor)
    seen = {}
    cfg = runner.load_config([BASELINE], [*TINY, "trainer.max_steps=1", f"init_from=[{{file: {path}, map: {MAP}}}]"])
    runner.fit(
        cfg, tmp_path / "run", setup=lambda model: seen.update({k: v.clone() for k, v in model.state_dict().items()})
    )
    assert all(torch.equal(seen["encoder." + k[len("img_backbone.") :]], v) for k, v in donor.items())
    assert f"init_from[0]: {path}: loaded {len(donor)} tensors" in capsys.readouterr().out
    Path(path).unlink()  # a resumed run reads its checkpoint, not the file
    cfg = runner.load_config([BASELINE], [*TINY, "trainer.max_steps=2", f"init_from=[{{file: {path}, map: {MAP}}}]"])
    runner.fit(cfg, tmp_path / "run", resume=True)
    assert "init_from" not in capsys.readouterr().out


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("[{phase: teacher}]", r"init_from\[0\]: expected \{file: PATH, .*phase.*belong in a phase's overlay"),
        ("[{file: w.pth, map: {img_backbone.: encoder.}}]", r"init_from\[0\]\.map\.img_backbone\.: expected a prefix"),
        ("[{file: w.pth, map: {img_backbone.: model.encoder}}]", r"ending in '\.' maps onto one ending in '\.'"),
        ("[{file: w.pth, strict: yes please}]", r"init_from\[0\]\.strict: expected true or false"),
        ("[{file: w.pth, prefixes: [model]}]", r"init_from\[0\]: expected \{file: PATH"),
        ("{file: w.pth}", r"init_from: expected a list of \{file, map, strict\}"),
    ],
)
def test_config_mistakes_name_the_key(value, message):
    with pytest.raises(ConfigError, match=message):
        runner.load_config([BASELINE], [*TINY, f"init_from={value}"])


def test_phases_inherit_the_top_level_entries_and_may_drop_them():
    cfg = runner.load_config(
        [BASELINE],
        [
            *TINY,
            f"init_from=[{{file: w.pth, map: {MAP}}}]",
            "phases={a: {}, b: {'~init_from': null, init_from: [{phase: a}, {file: v.pth, map: {'': model.}}]}}",
        ],
    )
    a, b = phase_specs(cfg)
    assert a.config["init_from"] == cfg["init_from"] and a.init_from == ()
    assert "init_from" not in b.config
    assert [(e.phase, e.file, e.map) for e in b.init_from] == [("a", None, ()), (None, "v.pth", (("", ""),))]
    assert parse_init_from(cfg["init_from"], None, "init_from")[0].map == (("img_backbone.", "encoder."),)
