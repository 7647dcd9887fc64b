"""Regenerate every claims table in the READMEs and RESULTS.md files from the per-seed JSON files under ``results/``.

A table is marked in the markdown by two comments; everything between them is generated::

    <!-- claims-table: queryocc_claims -->
    | claim | measured here | ... |
    <!-- /claims-table -->

Its spec, under the same name in ``results/claims_tables.yaml``, gives the folder the JSON globs are relative to
(``results:``), the header (``columns:``, a trailing ``:`` right-aligns a column, as ``--:`` does) and the rows: one
list of cells each. A cell is text with fields ``[[op arg ...]]`` computed from the files ``<stem>-seed*.json``
(``occplug.run.bench.write_seed_result``'s files; a stem is a path below ``results:``, without ``-seed*.json``):

* ``[[ms STEM KEY]]``: mean ± sample std over the seeds of ``values[KEY]`` (``occplug.run.bench.mean_std``);
* ``[[mean STEM KEY]]``: the mean alone (a floor that does not vary by seed);
* ``[[n STEM]]``: how many seeds;
* ``[[diff A B KEY]]``: mean of A minus mean of B, signed;
* ``[[wins A B KEY]]``: ``k of n seeds`` on which A's value is above B's (the seeds both have);
* ``[[share A FLOOR CEILING KEY]]``: A's mean as a share of the ceiling's margin over the floor,
  ``100 (A - FLOOR) / (CEILING - FLOOR)`` of the three means, in percent (``+12.3 %``; negative below the floor).

A metric key with a space is quoted (``[[ms supervision/base "Sem.IoU w/o others"]]``). Commands::

    python scripts/claims_tables.py            # rewrite every marked table in place
    python scripts/claims_tables.py --check    # exit 1 naming each table that differs from its JSON files

A table whose numbers have no committed JSON is not marked, and says so in its own text. A spec or marker that
does not resolve (an unknown table, a stem with no files, a key a file lacks) is one ``error:`` line, exit 2, and
nothing is rewritten.
"""

from __future__ import annotations

import argparse
import json
import re
import shlex
import statistics
import subprocess
import sys
from pathlib import Path
from typing import Any

import yaml

from occplug.run.bench import mean_std

ROOT = Path(__file__).resolve().parents[1]
SPEC = Path("results/claims_tables.yaml")
BLOCK = re.compile(r"(<!-- claims-table: (?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- /claims-table -->)", re.S)
FIELD = re.compile(r"\[\[([^\]]+)\]\]")


class SpecError(Exception):
    """A spec, marker or result file that does not resolve: the message is the whole ``error:`` line."""


def seed_values(root: Path, results: str, stem: str, key: str) -> dict[int, float]:
    """``{seed: values[key]}`` of ``<results>/<stem>-seed*.json`` (a ``null`` value, NaN in the run, left out)."""
    files = seed_files(root, results, stem)
    out = {}
    for path in files:
        record = json.loads(path.read_text())
        values = record.get("values", {})
        if key not in values:
            raise SpecError(f"{path.relative_to(root)}: no values[{key!r}] (it has {sorted(values)})")
        if values[key] is not None:
            out[int(record["seed"])] = float(values[key])
    return out


def seed_files(root: Path, results: str, stem: str) -> list[Path]:
    files = sorted((root / results).glob(f"{stem}-seed*.json"))
    if not files:
        raise SpecError(f"no file matches {results}/{stem}-seed*.json")
    return files


ARITY = {"ms": 2, "mean": 2, "n": 1, "diff": 3, "wins": 3, "share": 4}


def field(root: Path, results: str, text: str) -> str:
    """The value of one ``[[op arg ...]]`` field."""
    op, *args = shlex.split(text)
    if ARITY.get(op) != len(args):
        raise SpecError(
            f"field [[{text}]]: expected ms/mean STEM KEY, n STEM, diff/wins A B KEY or share A FLOOR CEILING KEY"
        )
    if op == "share":
        a, floor, ceiling = (statistics.mean(seed_values(root, results, stem, args[3]).values()) for stem in args[:3])
        if ceiling == floor:
            raise SpecError(f"field [[{text}]]: the ceiling equals the floor")
        return f"{100.0 * (a - floor) / (ceiling - floor):+.1f} %"
    if op == "n":
        return str(len(seed_files(root, results, args[0])))
    if op in ("ms", "mean"):
        values = list(seed_values(root, results, *args).values())
        return mean_std(values) if op == "ms" else f"{statistics.mean(values):.2f}"
    a, b = (seed_values(root, results, stem, args[2]) for stem in args[:2])
    if op == "diff":
        return f"{statistics.mean(a.values()) - statistics.mean(b.values()):+.2f}"
    both = sorted(a.keys() & b.keys())
    if not both:
        raise SpecError(f"field [[{text}]]: {args[0]} and {args[1]} share no seed")
    return f"{sum(a[s] > b[s] for s in both)} of {len(both)} seeds"


def render(root: Path, name: str, spec: dict[str, Any]) -> str:
    """The markdown table ``name`` (header, rule, one line per row), each line ending in a newline."""
    try:
        results, columns, rows = str(spec["results"]), spec["columns"], spec["rows"]
    except (KeyError, TypeError) as err:
        raise SpecError(f"{SPEC}: table {name}: needs results, columns and rows ({err})") from None
    head = [c.removesuffix(":") for c in columns]
    rule = ["--:" if c.endswith(":") else "---" for c in columns]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join(rule) + "|"]
    for k, row in enumerate(rows):
        if len(row) != len(columns):
            raise SpecError(f"{SPEC}: table {name}, row {k + 1}: {len(row)} cells for {len(columns)} columns")
        try:
            cells = [FIELD.sub(lambda m: field(root, results, m.group(1)), str(cell)) for cell in row]
        except SpecError as err:
            raise SpecError(f"{SPEC}: table {name}, row {k + 1}: {err}") from None
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def markdown_files(root: Path) -> list[Path]:
    """Every README.md and RESULTS.md of the checkout (git's list; every one under ``root`` outside git)."""
    listed = subprocess.run(["git", "ls-files", "*README.md", "*RESULTS.md"], cwd=root, capture_output=True, text=True)
    if listed.returncode == 0 and listed.stdout.strip():
        return [root / p for p in listed.stdout.split()]
    return sorted(p for n in ("README.md", "RESULTS.md") for p in root.rglob(n) if ".venv" not in p.parts)


def regenerate(root: Path) -> dict[Path, tuple[str, str, list[str]]]:
    """``{file: (old text, new text, names of the tables that differ)}`` for every file holding a marked table."""
    spec_path = root / SPEC
    try:
        specs = yaml.safe_load(spec_path.read_text()) or {}
    except (OSError, yaml.YAMLError) as err:
        raise SpecError(f"{spec_path}: cannot read the table specs ({err})") from None
    tables = {}
    out, used = {}, set()
    for path in markdown_files(root):
        text = path.read_text()
        differ = []

        def replace(match: re.Match[str], path: Path = path, differ: list[str] = differ) -> str:
            name = match.group("name")
            if name not in specs:
                raise SpecError(f"{path.relative_to(root)}: claims table {name!r} has no spec in {SPEC}")
            used.add(name)
            if name not in tables:
                tables[name] = render(root, name, specs[name])
            if match.group("body") != tables[name]:
                differ.append(name)
            return match.group(1) + tables[name] + match.group(4)

        new = BLOCK.sub(replace, text)
        if new != text or differ or BLOCK.search(text):
            out[path] = (text, new, differ)
    unused = sorted(set(specs) - used)
    if unused:
        raise SpecError(f"{SPEC}: no README or RESULTS.md marks the tables {unused}")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python scripts/claims_tables.py",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--check", action="store_true", help="change nothing; exit 1 if a table differs")
    parser.add_argument("--root", type=Path, default=ROOT, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    try:
        found = regenerate(args.root)
    except SpecError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    stale = [(path, names) for path, (_, _, names) in found.items() if names]
    if args.check:
        for path, names in stale:
            print(f"{path.relative_to(args.root)}: {', '.join(names)} differ from their JSON files", file=sys.stderr)
        if stale:
            print("run: python scripts/claims_tables.py", file=sys.stderr)
            return 1
        print(f"{sum(len(BLOCK.findall(old)) for old, _, _ in found.values())} claims tables match their JSON files")
        return 0
    for path, (old, new, names) in found.items():
        if new != old:
            path.write_text(new)
            print(f"{path.relative_to(args.root)}: rewrote {', '.join(names)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
