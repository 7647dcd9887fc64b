"""``scripts/claims_tables.py``: every claims table in the READMEs and RESULTS.md files equals what its per-seed
JSON files give, and a number edited by hand (or a JSON file changed) is caught."""

from __future__ import annotations

import json
import shutil
import statistics
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

SPEC = """\
demo:
  results: results/m
  columns: ["claim", "here:", "seeds"]
  rows:
    - - "a beats b"
      - "[[ms row_a mIoU]] vs [[mean row_b mIoU]] ([[diff row_a row_b mIoU]], ahead on [[wins row_a row_b mIoU]])"
      - "[[n row_a]]"
"""
README = "# m\n\n<!-- claims-table: demo -->\n<!-- /claims-table -->\n\nAfter the table.\n"


def _seed(folder: Path, row: str, seed: int, value: float | None) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    record = {"row": row, "seed": seed, "values": {"mIoU": value}, "settings": {}, "command": ["x"], "commit": None}
    (folder / f"{row}-seed{seed}.json").write_text(json.dumps(record))


@pytest.fixture
def tree(tmp_path):
    """A checkout-like folder: one README with one marked table, its spec and five JSON files."""
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "claims_tables.yaml").write_text(SPEC)
    (tmp_path / "README.md").write_text(README)
    for seed, (a, b) in enumerate([(10.0, 9.0), (12.0, 9.0), (8.0, 9.0)]):
        _seed(tmp_path / "results" / "m", "row_a", seed, a)
        _seed(tmp_path / "results" / "m", "row_b", seed, b)
    return tmp_path


def test_every_table_in_the_repository_matches_its_json_files(script, capsys):
    module = script("claims_tables")
    assert module.main(["--check"]) == 0, capsys.readouterr().err
    found = module.regenerate(ROOT)
    marked = {p.relative_to(ROOT).as_posix() for p, (old, _, _) in found.items() if module.BLOCK.search(old)}
    for method in ("queryocc", "duocc"):  # OccLE's accuracy table has no committed JSON: it says so, unmarked
        assert f"plugins/occplug_{method}/README.md" in marked


def test_a_table_is_written_from_its_json_and_a_hand_edit_is_caught(script, tree, capsys):
    module = script("claims_tables")
    assert module.main(["--root", str(tree)]) == 0
    text = (tree / "README.md").read_text()
    mean = statistics.mean([10.0, 12.0, 8.0])
    std = statistics.stdev([10.0, 12.0, 8.0])
    row = f"| a beats b | {mean:.2f} ± {std:.2f} vs 9.00 (+1.00, ahead on 2 of 3 seeds) | 3 |"
    assert text == README.replace("-->\n<!--", f"-->\n| claim | here | seeds |\n|---|--:|---|\n{row}\n<!--")
    assert module.main(["--root", str(tree), "--check"]) == 0
    (tree / "README.md").write_text(text.replace("9.00", "9.10"))  # a number edited by hand
    capsys.readouterr()
    assert module.main(["--root", str(tree), "--check"]) == 1
    assert "README.md: demo differ" in capsys.readouterr().err
    assert module.main(["--root", str(tree)]) == 0 and (tree / "README.md").read_text() == text  # round trip


def test_a_changed_json_file_makes_the_table_stale(script, tree):
    module = script("claims_tables")
    module.main(["--root", str(tree)])
    _seed(tree / "results" / "m", "row_a", 2, 20.0)
    assert module.main(["--root", str(tree), "--check"]) == 1


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: shutil.rmtree(t / "results" / "m"), "no file matches results/m/row_a-seed*.json"),
        (lambda t: (t / "README.md").write_text(README.replace("demo", "dmeo")), "claims table 'dmeo' has no spec"),
        (lambda t: (t / "README.md").write_text("# m\n"), "no README or RESULTS.md marks the tables ['demo']"),
    ],
)
def test_a_spec_that_does_not_resolve_is_one_error_line_and_writes_nothing(script, tree, capsys, edit, message):
    module = script("claims_tables")
    edit(tree)
    before = (tree / "README.md").read_text()
    code = module.main(["--root", str(tree)])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: ") and message in err and err.count("\n") == 1
    assert (tree / "README.md").read_text() == before


def test_share_is_the_rows_place_between_floor_and_ceiling(script, tree):
    module = script("claims_tables")
    for seed in range(3):
        _seed(tree / "results" / "m", "ceiling", seed, 20.0)
    spec = SPEC.replace(
        '"[[n row_a]]"', '"[[n row_a]]; [[share row_a row_b ceiling mIoU]], [[share row_b row_a ceiling mIoU]]"'
    )
    (tree / "results" / "claims_tables.yaml").write_text(spec)
    assert module.main(["--root", str(tree)]) == 0
    # row_a's mean 10, floor row_b 9, ceiling 20: 1 / 11 of the margin; row_b against row_a: -1 / 10
    assert "| 3; +9.1 %, -10.0 % |" in (tree / "README.md").read_text()
