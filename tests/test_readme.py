"""The root README is user documentation in one structure, and what it and the ``docs/`` pages say holds.

Checked instead of a line count: the sections in order; the two set-up commands exact and first (``.ci/run`` calls
the second verbatim); no commit hash or run provenance (that lives in ``results/``); the world section's knob table
agrees with the code's defaults and the ``testbed`` preset; the real-data block runs its steps in order; every
relative link of the README, ``docs/`` and ``results/`` resolves; every synthetic-world ``occplug fit`` command the
pages show passes ``occplug config validate``.
"""

from __future__ import annotations

import dataclasses
import inspect
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
#: the measurement pages (results/<method>/RESULTS.md, results/README.md and the claim folders' README.md files)
RESULTS = sorted((ROOT / "results").rglob("*.md"))

#: the root README's sections, in this order
SECTIONS = (
    "## Quick start",
    "## Concepts",
    "## Using it",
    "## The synthetic world",
    "## Real data sets",
    "## Methods",
    "## Results",
    "## Writing a plugin",
    "## Documentation",
)
#: the README contract's two commands: 1 installs a CPU torch and trains on the synthetic world, 2 is CI's
COMMANDS = (
    "pip install torch==2.13.0 -e . && occplug fit -c configs/baseline.yaml",
    'pip install torch==2.14.1 torchvision==0.29.1 -e ".[dev]" && python -m pytest -q',
)
#: run provenance and measurement history: they belong in results/, not in the README
PROVENANCE = (
    "beside two other jobs",
    "beside other jobs",
    "beside one other job",
    "load average",
    "measured here",
    "nothing else running",
    "on this 2-core",
    "on this machine",
    "at commit",
)
#: a 7-40 digit hex word with a letter and a digit in it (a commit); "1e-3" or "2048" are not
HASH = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines()


def _body(lines: list[str], heading: str) -> list[str]:
    start = next(i for i, line in enumerate(lines) if line.startswith(heading))
    end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("## ")), len(lines))
    return lines[start + 1 : end]


def _blocks(lines: list[str]) -> list[list[str]]:
    """The fenced code blocks, each as its lines without the fences."""
    blocks, inside = [], None
    for line in lines:
        if line.startswith("```"):
            if inside is None:
                inside = []
            else:
                blocks.append(inside)
                inside = None
        elif inside is not None:
            inside.append(line)
    return blocks


def _commands(block: list[str]) -> list[str]:
    """A bash block's commands: continuation lines joined, comments and blank lines dropped."""
    joined, out = "", []
    for line in block:
        line = re.split(r"\s+#(?:\s|$)", line)[0].rstrip() if not line.lstrip().startswith("#") else ""
        if line.endswith("\\"):
            joined += line[:-1].strip() + " "
            continue
        command = (joined + line.strip()).strip()
        joined = ""
        if command:
            out.append(command)
    return out


def _headings(lines: list[str]) -> list[str]:
    return [line for line in lines if line.startswith("## ")]


def test_the_sections_are_present_in_order():
    headings = _headings(_lines(README))
    at = [next((k for k, h in enumerate(headings) if h.startswith(s)), None) for s in SECTIONS]
    assert None not in at and at == sorted(at), f"README sections {headings}, expected in order {SECTIONS}"


def test_the_two_commands_are_exact_and_first():
    lines = _lines(README)
    first = _blocks(lines)[0]
    assert _commands(first) == list(COMMANDS), f"the README's first code block is {first}"
    assert lines.index("```bash") > next(i for i, line in enumerate(lines) if line == "## Quick start")
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert COMMANDS[1] in ci, ".ci/run no longer calls the README's test command verbatim"


def test_no_commit_hashes_or_run_provenance():
    text = README.read_text()
    hashes = HASH.findall(text)
    assert not hashes, f"the README names commits {hashes}; provenance goes to results/"
    # the generated status table words its verdicts from results/claims_tables.yaml; the prose around it is ours
    prose = re.sub(r"<!-- claims-table: .*?<!-- /claims-table -->", "", text, flags=re.S).lower()
    found = [word for word in PROVENANCE if word in prose]
    assert not found, f"the README holds run provenance {found}; it goes to results/"


def _table(lines: list[str]) -> list[list[str]]:
    rows = [line for line in lines if line.startswith("|")]
    return [[cell.strip() for cell in row.strip("|").split("|")] for row in rows[2:]]


def _knob_table() -> dict[str, list[str]]:
    body = _body(_lines(README), "## The synthetic world")
    start = next(i for i, line in enumerate(body) if line.startswith("| knob"))
    end = next(i for i in range(start, len(body)) if not body[i].startswith("|"))
    return {row[0].split("`")[1]: row for row in _table(body[start:end])}


def _number_list(cell: str) -> list[float]:
    return [float(x) for x in re.findall(r"-?\d+(?:\.\d+)?", cell)]


def test_the_world_section_gives_every_knob_its_true_default_and_testbed_value():
    from occplug.data.synthetic import PRESETS, SyntheticWorldConfig
    from occplug.data.synthetic.datamodule import SyntheticDataModule

    knobs = _knob_table()
    names = {name.removeprefix("data.") for name in knobs}
    wanted = {"lidar_range_noise", "lidar_dropout", "ego_lane_speed_offset", "eval_frames_per_scene"}
    assert wanted | {"label_unit", "image_size"} <= names, f"the knob table lacks {wanted - names}"
    defaults = {f.name: f.default for f in dataclasses.fields(SyntheticWorldConfig)}
    testbed = PRESETS["testbed"]
    for name, (_, default, on_testbed, why) in knobs.items():
        key = name.removeprefix("data.")
        assert why, f"knob {name}: no reason given"
        if key == "label_unit":  # a data-module argument, not a world knob
            declared = inspect.signature(SyntheticDataModule).parameters[key].default
            assert default.strip("`") == declared and on_testbed.strip("`") == declared, name
            continue
        assert key in defaults, f"knob {name} is not a SyntheticWorldConfig field"
        true_default, true_testbed = defaults[key], getattr(testbed, key)
        as_list = (lambda v: [float(x) for x in v]) if isinstance(true_default, tuple) else (lambda v: [float(v)])
        assert _number_list(default) == as_list(true_default), f"knob {name}: default {default} != {true_default}"
        assert _number_list(on_testbed) == as_list(true_testbed), f"knob {name}: testbed {on_testbed} != {true_testbed}"
        if name.startswith("data."):  # a knob named as a config key is one the data module takes
            assert key in inspect.signature(SyntheticDataModule).parameters, f"data.{key} is no data-module argument"
    presets = " ".join(row[0] for row in _table(_body(_lines(README), "## The synthetic world")))
    for name in ("aligned", "testbed", "default", "tiny"):
        assert f"`{name}`" in presets, f"the presets table lacks {name}"
        assert name in PRESETS


def test_the_real_data_block_prepares_trains_and_evaluates_in_order():
    (block, *_) = _blocks(_body(_lines(README), "## Real data sets"))
    commands = _commands(block)
    first = {
        step: next((i for i, c in enumerate(commands) if c.startswith(step)), None)
        for step in ("occplug data check nuscenes", "occplug data prepare nuscenes", "occplug fit", "occplug validate")
    }
    assert None not in first.values() and list(first.values()) == sorted(first.values()), commands
    fit = commands[first["occplug fit"]]
    assert "data.index=data/nuscenes/occplug_index" in fit and "occplug/data/occ3d_nuscenes" in fit
    assert any(c.startswith("occplug eval") for c in commands), "the block does not score saved predictions"
    assert any("occplug/data/semantickitti" in c for c in commands), "the block does not train on SemanticKITTI"


def _slug(heading: str) -> str:
    text = re.sub(r"[^\w\- ]", "", heading.lstrip("#").strip().lower())
    return text.replace(" ", "-")


@pytest.mark.parametrize("page", [README, *DOCS, *RESULTS], ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page):
    broken = []
    for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
        if re.match(r"[a-z]+://", target) or target.startswith("mailto:"):
            continue
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            broken.append(target)
        elif anchor and file.suffix == ".md":
            slugs = {_slug(line) for line in _lines(file) if line.startswith("#")}
            if anchor not in slugs:
                broken.append(target)
    assert not broken, f"{page.relative_to(ROOT)}: links that lead nowhere: {broken}"


def _fit_commands(page: Path) -> list[list[str]]:
    """Each ``occplug fit -c ...`` a page shows on the synthetic world, as ``config validate`` arguments."""
    out = []
    for block in _blocks(_lines(page)):
        for command in _commands(block):
            if not command.startswith("occplug fit -c") or re.search(r"\.\.\.|<|\[|\$", command):
                continue
            args = shlex.split(command)[2:]
            if "--run-dir" in args:
                at = args.index("--run-dir")
                del args[at : at + 2]
            out.append(args)
    return out


def test_the_pages_fit_commands_are_valid_configs(capsys):
    from occplug.cli import main

    commands = [args for page in (README, *DOCS) for args in _fit_commands(page)]
    assert len(commands) >= 10, f"found only {len(commands)} fit commands in the README and docs/"
    failed = []
    for args in commands:
        if main(["config", "validate", *args]) != 0:
            failed.append(" ".join(args))
    assert not failed, f"these documented commands do not validate: {failed}\n{capsys.readouterr().err}"
