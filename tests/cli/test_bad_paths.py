"""Every path argument of every command × every kind of bad path: one ``error:`` line, exit 2, nothing written.

Kinds of bad path: a file where a folder is expected, a folder where a file is expected, a path below a
file (what an unwritable place is for root, who may write anywhere else), a missing parent folder, and
(not as root) a folder without write permission.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from occplug.cli import main

ROOT = Path(__file__).resolve().parents[2]
BASELINE = str(ROOT / "configs" / "baseline.yaml")

# What each argument expects: an input folder / file / either, an output folder / file, or a -c config.
IN_DIR, IN_FILE, IN_ANY, OUT_DIR, OUT_FILE, CONFIG = "in_dir", "in_file", "in_any", "out_dir", "out_file", "config"
RUN_DIR = "run_dir"  # an output folder whose missing parents are created (as the default runs/<time> is)

#: (command line with {P} for the bad path, {DIR} for a good empty folder, {FILE} for a good file; what {P} is)
ARGUMENTS: list[tuple[str, str]] = [
    ("fit -c {P}", CONFIG),
    ("fit -c BASELINE --run-dir {P}", RUN_DIR),
    ("fit --resume {P}", IN_DIR),
    ("fit -c BASELINE -c occplug/data/occ3d_nuscenes data.root={P} --run-dir {DIR}/run", IN_DIR),
    ("fit -c BASELINE -c occplug/data/semantickitti data.root={P} --run-dir {DIR}/run", IN_DIR),
    ("validate --ckpt {P}", IN_FILE),
    ("validate -c {P} --ckpt {FILE}", CONFIG),
    ("validate --ckpt {FILE} --json {P}", OUT_FILE),
    ("test --ckpt {P}", IN_FILE),
    ("test --ckpt {FILE} --json {P}", OUT_FILE),
    ("predict --ckpt {P} --out {DIR}", IN_FILE),
    ("predict --ckpt {FILE} --out {P}", OUT_DIR),
    ("predict -c {P} --ckpt {FILE} --out {DIR}", CONFIG),
    ("config show -c {P}", CONFIG),
    ("config validate -c {P}", CONFIG),
    ("data synth --preset tiny --out {P}", OUT_DIR),
    ("data prepare nuscenes --root {P} --version v1.0-mini --out {DIR}", IN_DIR),
    ("data prepare nuscenes --root {DIR} --version v1.0-mini --occ {P} --out {DIR}", IN_DIR),
    ("data prepare nuscenes --root {DIR} --version v1.0-mini --splits {P} --out {DIR}", IN_FILE),
    ("data prepare nuscenes --root {DIR} --version v1.0-mini --out {P}", OUT_DIR),
    ("data check nuscenes --root {P} --version v1.0-mini", IN_DIR),
    ("data check nuscenes --root {DIR} --version v1.0-mini --occ {P}", IN_DIR),
    ("data check nuscenes --root {DIR} --version v1.0-mini --splits {P}", IN_FILE),
    ("data check semantickitti --root {P}", IN_DIR),
    ("data check semantickitti --root {DIR} --splits {P}", IN_FILE),
    ("data check index --index {P}", IN_ANY),
    ("data check index --index {DIR} --root {P}", IN_DIR),
    ("data pseudo-labels nuscenes --index {P} --depth {DIR} --out {DIR}", IN_ANY),
    ("data pseudo-labels nuscenes --index {DIR} --root {P} --depth {DIR} --out {DIR}", IN_DIR),
    ("data pseudo-labels nuscenes --index {DIR} --depth {P} --out {DIR}", IN_DIR),
    ("data pseudo-labels nuscenes --index {DIR} --semantics {P} --out {DIR}", IN_DIR),
    ("data pseudo-labels nuscenes --index {DIR} --semantics {DIR} --mapping {P} --out {DIR}", IN_FILE),
    ("data pseudo-labels nuscenes --index {DIR} --depth {DIR} --out {P}", OUT_DIR),
    ("eval --pred {P} --gt {DIR}", IN_DIR),
    ("eval --pred {DIR} --gt {P}", IN_DIR),
    ("eval --pred {DIR} --gt {DIR} --json {P}", OUT_FILE),
    ("eval --pred {DIR} --gt {DIR} --metric rayiou --origins {P}", IN_FILE),
    ("eval --pred {DIR} --gt {DIR} --metric rayiou --index {P}", IN_ANY),
    ("viz sample -c {P} --out {DIR}", CONFIG),
    ("viz sample -c BASELINE --out {P}", OUT_DIR),
    ("viz sample --ckpt {P} --out {DIR}", IN_FILE),
    ("viz sample -c BASELINE --out {DIR} --rerun {P}", OUT_FILE),
    ("viz run {P}", IN_DIR),
    ("viz run {DIR} --out {P}", OUT_DIR),
    ("export --ckpt {P} --format onnx --out {DIR}/model.onnx", IN_FILE),
    ("export --ckpt {FILE} --format onnx --out {P}", OUT_FILE),
    ("bench BASELINE --preset tiny -o {P}", OUT_FILE),
]

#: The bad paths each expectation meets.
KINDS = {
    IN_DIR: ("a_file", "below_a_file", "missing_parent"),
    IN_FILE: ("a_folder", "below_a_file", "missing_parent"),
    IN_ANY: ("below_a_file", "missing_parent"),
    CONFIG: ("a_folder", "below_a_file", "missing_parent"),
    OUT_DIR: ("a_file", "below_a_file", "missing_parent", "unwritable"),
    RUN_DIR: ("a_file", "below_a_file", "unwritable"),
    OUT_FILE: ("a_folder", "below_a_file", "missing_parent", "unwritable"),
}

#: The words the error line says for each kind (besides naming the path); "is not a folder" is the
#: data modules' own line about ``data.root``.
SAYS = {
    "a_file": ("expected a folder", "is not a folder"),
    "a_folder": ("expected a",),  # "a file" / "a config file"
    "below_a_file": ("is a file, not a folder", "is not a folder"),
    "missing_parent": ("no such", "does not exist", "not found", "is not a folder"),
    "unwritable": ("permission denied",),
}

CASES = [
    pytest.param(line, kind, id=f"{line.split(' {P}')[0].replace(' ', '_')}-{kind}")
    for line, expects in ARGUMENTS
    for kind in KINDS[expects]
]


def _tree(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


@pytest.fixture
def sandbox(tmp_path, monkeypatch):
    """A working folder with a file, an empty folder and a file to pass where a good file is needed."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "a_file.txt").write_text("not a folder\n")
    (tmp_path / "good_file.ckpt").write_text("x\n")
    (tmp_path / "empty").mkdir()
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    yield tmp_path
    locked.chmod(0o700)


def _bad_path(root: Path, kind: str) -> Path:
    return {
        "a_file": root / "a_file.txt",
        "a_folder": root / "empty",
        "below_a_file": root / "a_file.txt" / "inside",
        "missing_parent": root / "no_such_folder" / "x",
        "unwritable": root / "locked" / "x",
    }[kind]


@pytest.mark.parametrize(("line", "kind"), CASES)
def test_a_bad_path_is_one_error_line(sandbox, capsys, line, kind):
    if kind == "unwritable" and os.geteuid() == 0:
        pytest.skip("root writes anywhere (below_a_file covers an unwritable place)")
    bad = _bad_path(sandbox, kind)
    argv = [
        arg.replace("{P}", str(bad))
        .replace("{DIR}", str(sandbox / "empty"))
        .replace("{FILE}", str(sandbox / "good_file.ckpt"))
        for arg in line.split()
    ]
    argv = [BASELINE if arg == "BASELINE" else arg for arg in argv]
    before = _tree(sandbox)
    code = main(argv)
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err
    message = lines[0]
    assert str(bad) in message or bad.name in message, message  # names the path
    assert any(s in message for s in SAYS[kind]), message
    assert _tree(sandbox) == before  # nothing created, nothing half-written


def test_an_unwritable_folder_is_reported_even_where_permissions_do_not_bind(tmp_path, monkeypatch):
    """Root may write anywhere, so the permission check is exercised with ``os.access`` saying no."""
    from occplug.cli import paths
    from occplug.cli.errors import UsageError

    monkeypatch.setattr(paths.os, "access", lambda path, mode: False)
    with pytest.raises(UsageError, match=r"^--out .*/x: cannot write in .* \(permission denied\)$"):
        paths.output_dir("--out", tmp_path / "x")
    with pytest.raises(UsageError, match=r"^--json .*/m.json: cannot write in .* \(permission denied\)$"):
        paths.output_file("--json", tmp_path / "m.json")
    with pytest.raises(UsageError, match=r"^--out .*: cannot write in it \(permission denied\)$"):
        paths.output_dir("--out", tmp_path)


def test_good_paths_pass_and_come_back():
    from occplug.cli import paths

    assert paths.input_dir("--gt", ROOT) == ROOT
    assert paths.input_file("-c", BASELINE) == Path(BASELINE)
    assert paths.output_file("--json", ROOT / "new.json") == ROOT / "new.json"
    paths.config_refs([BASELINE, "occplug/data/synthetic"])


def test_a_run_directory_gets_its_missing_parents(tmp_path):
    """``fit --run-dir runs/smoke`` works in a fresh clone, where ``runs/`` does not exist yet."""
    from occplug.cli import paths

    target = tmp_path / "runs" / "deeper" / "smoke"
    assert paths.output_dir("--run-dir", target, make_parents=True) == target
    assert not (tmp_path / "runs").exists()  # checked, not created: fit creates it once everything is built
