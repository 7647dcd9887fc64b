"""Config YAML: YAML 1.2 numbers in files and overrides, reading within limits, one error line naming the file,
numbers in range at validation (issue 56 item 1, issue 57 item 5)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import yaml

from occplug.cli import main
from occplug.config import ConfigError, compose, phase_specs, read_config, validate
from occplug.config.yamlio import (
    MAX_INTERPOLATION_DEPTH,
    MAX_NODES,
    check_interpolations,
    dump_yaml,
    parse_yaml,
)
from occplug.plugins import get_registry
from occplug.run import runner

ROOT = Path(__file__).resolve().parents[2]
BASELINE = str(ROOT / "configs" / "baseline.yaml")


def _error_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err  # one line, no traceback
    return lines[0]


# ----------------------------------------------------------------------------- YAML 1.2 numbers
def test_exponent_and_leading_dot_numbers_are_floats_in_a_file(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text(f"base: [{BASELINE}]\noptimizer: {{lr: 2e-4, weight_decay: 1e-3}}\nmodel: {{x: .5}}\n")
    data = compose([str(path)]).data
    assert data["optimizer"] == {"type": "adamw", "lr": 2e-4, "weight_decay": 1e-3}
    assert data["model"]["x"] == 0.5 and isinstance(data["model"]["x"], float)


@pytest.mark.parametrize(("raw", "value"), [("1e-3", 1e-3), ("2e-4", 2e-4), (".5", 0.5), ("-1E+2", -100.0)])
def test_exponent_and_leading_dot_numbers_are_floats_as_overrides(raw, value):
    got = compose([BASELINE], [f"optimizer.lr={raw}"]).data["optimizer"]["lr"]
    assert got == value and isinstance(got, float)


def test_yaml_1_2_booleans_and_strings():
    """Only true/false are booleans (YAML 1.1's yes/no/on/off are strings); a string stays one after a dump."""
    assert parse_yaml("a: yes\nb: off\nc: true\nd: 0o17\ne: 017", "t") == {
        "a": "yes",
        "b": "off",
        "c": True,
        "d": 15,
        "e": 17,
    }
    tricky = {
        "s": ["1e-3", "yes", "On", "1:30", "null", ".inf", "~", "0o17", ""],
        "n": [1e-3, 2e-4, 0.5, 1e300, 2e-20, -1.5e-7, None, True],
        "no": "key",
    }
    assert parse_yaml(dump_yaml(tricky), "dump") == tricky
    assert yaml.safe_load(dump_yaml(tricky)) == tricky  # a YAML 1.1 reader (a script on a run's config.yaml) too


def test_config_validate_accepts_a_paper_learning_rate_end_to_end(tmp_path, capsys):
    assert main(["config", "validate", "-c", BASELINE, "optimizer.lr=1e-3"]) == 0
    path = tmp_path / "paper.yaml"
    path.write_text(f"base: [{BASELINE}]\noptimizer: {{lr: 2e-4}}\n")
    assert main(["config", "validate", "-c", str(path)]) == 0
    assert main(["config", "show", "-c", str(path), "--explain", "optimizer.lr"]) == 0
    assert f"optimizer.lr: set by {path}" in capsys.readouterr().out
    assert runner.load_config([str(path)], ["optimizer.weight_decay=.5"])["optimizer"]["lr"] == 2e-4


# ----------------------------------------------------------------------------- reading within limits
def _alias_bomb(levels: int = 9) -> str:
    lines = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for i in range(1, levels):
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]")
    return "\n".join(lines) + "\n"


@pytest.mark.timeout(20)
def test_an_alias_bomb_ends_in_one_line(tmp_path, capsys):
    path = tmp_path / "bomb.yaml"
    path.write_text(_alias_bomb())  # 9**9 lols once expanded
    with pytest.raises(ConfigError, match=rf"^{path}: the document expands to more than {MAX_NODES:,} nodes"):
        read_config(path)
    assert main(["config", "show", "-c", str(path)]) == 2
    assert _error_line(capsys).startswith(f"error: {path}: the document expands")


def test_aliases_within_the_bound_are_plain_shared_data():
    data = parse_yaml("a: &x {k: [1, 2]}\nb: *x\nc: [*x, *x]\n", "t")
    assert data == {"a": {"k": [1, 2]}, "b": {"k": [1, 2]}, "c": [{"k": [1, 2]}, {"k": [1, 2]}]}


def test_a_recursive_alias_and_deep_nesting_are_refused():
    with pytest.raises(ConfigError, match="^r: an alias refers to a node that contains it"):
        parse_yaml("a: &a [1, *a]\n", "r")
    with pytest.raises(ConfigError, match=r"^d: .*nested too deeply"):
        parse_yaml("[" * 100 + "]" * 100, "d")
    with pytest.raises(ConfigError, match=r"^d: nested too deeply"):
        parse_yaml("[" * 5000 + "]" * 5000, "d")  # deeper than Python's recursion: still one line


def _interpolation_bomb(tmp_path: Path, levels: int) -> Path:
    lines = [f"base: [{BASELINE}]", 'x0: "aaaaaaaaaa"']
    lines += [f'x{i}: "${{x{i - 1}}}${{x{i - 1}}}"' for i in range(1, levels)]
    path = tmp_path / "ibomb.yaml"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.timeout(20)
def test_an_interpolation_bomb_ends_in_one_line_naming_the_key_and_file(tmp_path, capsys):
    path = _interpolation_bomb(tmp_path, 40)  # 10 * 2**39 characters, 2**40 resolutions if resolved
    with pytest.raises(ConfigError, match=rf"^x\d+: .*\(set by {path}\)$"):
        compose([str(path)]).resolved()
    assert main(["config", "show", "-c", str(path), "--no-validate"]) == 2
    _error_line(capsys)


def test_an_interpolation_chain_is_bounded_in_depth():
    chain = {"k0": 1, **{f"k{i}": f"${{k{i - 1}}}" for i in range(1, MAX_INTERPOLATION_DEPTH + 5)}}
    with pytest.raises(ConfigError, match=rf"^k{MAX_INTERPOLATION_DEPTH + 1}: interpolations nest"):
        check_interpolations(chain)
    ok = {"k0": 1, **{f"k{i}": f"${{k{i - 1}}}" for i in range(1, MAX_INTERPOLATION_DEPTH + 1)}}
    check_interpolations(ok)  # the bound itself is allowed
    relative = {"m": {"k0": 1, **{f"k{i}": f"${{.k{i - 1}}}" for i in range(1, MAX_INTERPOLATION_DEPTH + 2)}}}
    with pytest.raises(ConfigError, match=rf"^m.k{MAX_INTERPOLATION_DEPTH + 1}: interpolations nest"):
        check_interpolations(relative)  # relative references (${.key}, ${..key}) are followed too
    up = {"k0": 1, "m": {f"k{i}": f"${{..k{i - 1}}}" if i == 1 else f"${{.k{i - 1}}}" for i in range(1, 40)}}
    with pytest.raises(ConfigError, match=rf"^m.k{MAX_INTERPOLATION_DEPTH + 1}: interpolations nest"):
        check_interpolations(up)


def test_ordinary_interpolations_still_resolve():
    data = {"g": {"r": [1, 2]}, "m": {"a": "${g}", "b": "${.a}", "c": "${..g.r[0]}", "d": "x${g.r.1}y"}}
    check_interpolations(data)
    assert compose([], data=data).resolved()["m"] == {"a": {"r": [1, 2]}, "b": {"r": [1, 2]}, "c": 1, "d": "x2y"}


BAD_FILES = {
    "latin1": (b"seed: 1\nname: caf\xe9\n", "line 2: not UTF-8 text (byte 0xe9 at offset 17)"),
    "invalid": (b"a: [1, 2\nb: 3\n", "line 2: invalid YAML: expected ',' or ']'"),
    "python_tag": (
        b"a: !!python/object/apply:os.system [touch MARKER]\n",
        "line 1: tag '!!python/object/apply:os.system' is not allowed",
    ),
    "duplicate": (b"seed: 1\nseed: 2\n", 'line 2: invalid YAML: found duplicate key "seed"'),
    "not_a_mapping": (b"- 1\n- 2\n", "a config file must be a mapping at the top level, got list"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_every_read_error_is_one_line_naming_the_file(case, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    content, message = BAD_FILES[case]
    path = tmp_path / "bad.yaml"
    path.write_bytes(content)
    with pytest.raises(ConfigError) as caught:
        read_config(path)
    assert str(caught.value) == f"{path}: {message}" or str(caught.value).startswith(f"{path}: {message}")
    assert "\n" not in str(caught.value)
    assert main(["config", "show", "-c", str(path)]) == 2
    assert _error_line(capsys).startswith(f"error: {path}: {message}")
    assert not (tmp_path / "MARKER").exists()  # the tag was never constructed


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_a_broken_run_config_on_resume_is_one_line_and_writes_nothing(case, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "last.ckpt").write_bytes(b"not a checkpoint")
    (run / "config.yaml").write_bytes(BAD_FILES[case][0])
    before = sorted(str(p.relative_to(run)) for p in run.rglob("*"))
    assert main(["fit", "--resume", str(run)]) == 2
    assert _error_line(capsys).startswith(f"error: {run / 'config.yaml'}: {BAD_FILES[case][1]}")
    assert sorted(str(p.relative_to(run)) for p in run.rglob("*")) == before
    assert (run / "config.yaml").read_bytes() == BAD_FILES[case][0]
    assert not (tmp_path / "MARKER").exists()


def test_an_alias_bomb_in_a_run_config_on_resume_is_one_line(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text(_alias_bomb())
    assert main(["fit", "--resume", str(run)]) == 2
    assert "the document expands to more than" in _error_line(capsys)


# ----------------------------------------------------------------------------- numbers in range
@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("optimizer.lr=.inf", "optimizer.lr: expected a finite number, got float inf"),
        ("optimizer.lr=.nan", "optimizer.lr: expected a finite number, got float nan"),
        ("optimizer.weight_decay=-.inf", "optimizer.weight_decay: expected a finite number, got float -inf"),
        ("trainer.gradient_clip_val=.inf", "trainer.gradient_clip_val: expected a finite number, got float inf"),
        (
            "model.supervision.voxel_labels.weight=.inf",
            "model.supervision.voxel_labels.weight: expected a finite number, got float inf",
        ),
        (
            "model.supervision.voxel_labels.class_weights=[1.0, .inf]",
            "model.supervision.voxel_labels.class_weights: expected every element a finite number",
        ),
        ("model.encoder.out_channels=18446744073709551617", "model.encoder.out_channels: expected an int that fits"),
        ("seed=18446744073709551616", "seed: expected an int in [0, 2**32 - 1] (what NumPy seeds), got int"),
        ("seed=-1", "seed: expected an int in [0, 2**32 - 1]"),
        ("seed=4294967296", "seed: expected an int in [0, 2**32 - 1]"),
    ],
)
def test_numbers_out_of_range_are_refused_at_validate(override, message, capsys):
    with pytest.raises(ConfigError) as caught:
        validate(compose([BASELINE], [override]).resolved(), get_registry())
    assert str(caught.value).startswith(message), str(caught.value)
    assert main(["config", "validate", "-c", BASELINE, override]) == 2
    assert _error_line(capsys).startswith(f"error: {message}")


def test_numbers_at_the_edges_of_their_range_are_accepted():
    cfg = compose([BASELINE], ["seed=4294967295", "optimizer.lr=1e-300", "trainer.gradient_clip_val=1e300"]).resolved()
    validate(cfg, get_registry())
    assert math.isfinite(cfg["trainer"]["gradient_clip_val"])


def test_a_phase_name_with_a_trailing_newline_is_refused(tmp_path):
    base = compose([BASELINE]).resolved()
    with pytest.raises(ConfigError) as caught:
        phase_specs({**base, "phases": {"teacher\n": {}}})
    assert str(caught.value).startswith("phases: phase name 'teacher\\n': a phase name is letters")
    assert "\n" not in str(caught.value)
    path = tmp_path / "phased.yaml"
    path.write_text(f'base: [{BASELINE}]\nphases: {{"teacher\\n": {{trainer: {{max_epochs: 1}}}}}}\n')
    with pytest.raises(ConfigError, match="phase name 'teacher\\\\n'"):
        validate(compose([str(path)]).resolved(), get_registry())
    phase_specs({**base, "phases": {"teacher": {}}})  # the same name without the newline is fine


def test_data_synth_knobs_read_as_config_overrides_do(tmp_path, capsys):
    out = tmp_path / "w"
    assert main(["data", "synth", "--preset", "tiny", "--out", str(out), "image_noise=.inf"]) == 2
    assert _error_line(capsys) == "error: data.image_noise: expected a finite number, got float inf"
    assert main(["data", "synth", "--preset", "tiny", "--out", str(out), "image_size=[1e+2, 64]"]) == 2
    assert _error_line(capsys).startswith("error: data.image_size: expected list[int] or null, got list [100.0, 64]")
    assert not out.exists()
