"""What every ``occplug data check`` shares: the one-line error, the summary and the problem tally.

Each check (:func:`occplug.data.nuscenes.check.check_nuscenes`, :func:`~occplug.data.nuscenes.check.check_index`,
:func:`occplug.data.semantickitti.check.check_semantickitti`) walks **every** sample and reports either a short
summary (scenes / sequences and samples per split, files checked) or one line: the first offending file with the
number of files affected by the same problem, e.g.::

    data/occ3d/gts/scene-0003/<token>/labels.npz: no such file (40 of 34149 label files affected)

Nothing is written anywhere; every problem raises :class:`DataCheckError` (a
:class:`~occplug.data.formats.FormatError`) with one line.

The grid a check expects, unless told (``--shape``): the tree's own record (:data:`GRID_RECORD`, which
``occplug data synth`` writes beside its trees: :func:`write_grid_record` / :func:`read_grid_record`), else
what the layout itself tells (the shape most Occ3D label files share; SemanticKITTI's SSC grid).
"""

from __future__ import annotations

import json
import re
import stat
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from tqdm.auto import tqdm

from .formats import FormatError

__all__ = [
    "GRID_RECORD",
    "PROGRESS_DELAY",
    "CheckSummary",
    "DataCheckError",
    "Findings",
    "progress_bar",
    "read_grid_record",
    "write_grid_record",
]

#: The record of a tree's voxel grid, at its root: ``{"shape": [X, Y, Z], "range": [x0, y0, z0, x1, y1, z1],
#: "voxel_size": [vx, vy, vz]}`` (metres; the frame the tree's labels are in).
GRID_RECORD = "grid.json"

#: A progress bar appears once a check has run this long (seconds): large trees get one, small ones stay quiet.
PROGRESS_DELAY = 2.0
_PCD_POINT = 20  # bytes of a nuScenes .pcd.bin point (5 float32)
_VELO_POINT = 16  # bytes of a KITTI velodyne point (4 float32)


class DataCheckError(FormatError):
    """A data check found a problem (one line: the first offending file and how many files share the problem)."""


@dataclass
class CheckSummary:
    """What a passing check saw.

    Attributes:
        title: what was checked.
        splits: ``{split: (scenes or sequences, samples)}``.
        checked: ``{kind of file: count}``.
        notes: further lines (e.g. what was not checked).
    """

    title: str
    splits: dict[str, tuple[int, int]]
    checked: dict[str, int]
    notes: list[str] = field(default_factory=list)
    unit: str = "scene"

    def lines(self) -> list[str]:
        """The summary as printed by ``occplug data check``."""
        out = [f"ok: {self.title}"]
        out.extend(f"  {split}: {_count(scenes, self.unit)}, {_count(samples, 'sample')}"
                   for split, (scenes, samples) in self.splits.items())
        out.append("  checked: " + ", ".join(f"{n} {kind}" for kind, n in self.checked.items() if n))
        out.extend(f"  {note}" for note in self.notes)
        return out


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


class Findings:
    """Problems grouped by (category, kind); the first one found is reported with its count."""

    def __init__(self) -> None:
        self.checked: Counter[str] = Counter()
        self.problems: dict[tuple[str, str], list] = {}

    def check(self, category: str, n: int = 1) -> None:
        self.checked[category] += n

    def add(self, category: str, subject: str | Path, message: str, kind: str | None = None) -> None:
        """Record a problem; problems of one ``kind`` (default: the message, numbers blanked) are counted together."""
        key = (category, kind or re.sub(r"\d+", "#", message))
        if key in self.problems:
            self.problems[key][1] += 1
        else:
            self.problems[key] = [f"{subject}: {message}", 1]

    def add_error(self, category: str, path: Path, exc: FormatError) -> None:
        """A reader's one-line error (``<path>: <problem>``) as a problem of ``path``."""
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        prefix = f"{path}: "
        self.add(category, path, text[len(prefix) :] if text.startswith(prefix) else text)

    def stat(self, category: str, path: Path) -> int | None:
        """Count ``path`` as checked; its size, or None (a problem recorded) when missing or empty."""
        self.check(category)
        try:
            st = path.stat()
        except FileNotFoundError:
            self.add(category, path, "no such file")
            return None
        except OSError as exc:
            self.add(category, path, f"cannot be read ({exc.strerror})")
            return None
        if not stat.S_ISREG(st.st_mode):
            self.add(category, path, "not a regular file")
            return None
        size = st.st_size
        if size == 0:
            self.add(category, path, "empty file")
            return None
        return size

    def raise_first(self) -> None:
        if not self.problems:
            return
        (category, _), (line, count) = next(iter(self.problems.items()))
        text = f"{line} ({count} of {self.checked[category]} {category} affected)"
        others = list(self.problems.items())[1:]
        if others:
            (cat2, _), (line2, count2) = others[0]
            more = f" and {len(others) - 1} more kind(s) of problem" if len(others) > 1 else ""
            text += f"; also {line2} ({count2} of {self.checked[cat2]} {cat2}){more}"
        raise DataCheckError(text)


def write_grid_record(folder: str | Path, shape: Sequence[int], range_: Sequence[float],
                      voxel_size: Sequence[float]) -> Path:
    """Write :data:`GRID_RECORD` into ``folder`` (created); returns its path."""
    path = Path(folder) / GRID_RECORD
    path.parent.mkdir(parents=True, exist_ok=True)
    record = {"shape": [int(v) for v in shape], "range": [float(v) for v in range_],
              "voxel_size": [float(v) for v in voxel_size]}
    path.write_text(json.dumps(record, indent=2) + "\n")
    return path


def read_grid_record(folder: str | Path | None) -> tuple[tuple[int, int, int], Path] | None:
    """``((X, Y, Z), path)`` of the :data:`GRID_RECORD` in ``folder``, or None when there is none.

    Raises:
        DataCheckError: a record that is not JSON or has no ``shape`` of three positive integers (one line).
    """
    if folder is None or not (Path(folder) / GRID_RECORD).is_file():
        return None
    path = Path(folder) / GRID_RECORD
    try:
        shape = json.loads(path.read_text())["shape"]
        ok = len(shape) == 3 and all(isinstance(v, int) and v > 0 for v in shape)
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError):
        ok = False
    if not ok:
        raise DataCheckError(f'{path}: not a grid record; expected {{"shape": [X, Y, Z], ...}} (positive integers)')
    return (int(shape[0]), int(shape[1]), int(shape[2])), path


def progress_bar(total: int, desc: str, progress: bool) -> tqdm:
    return tqdm(total=total, desc=desc, unit="sample", delay=PROGRESS_DELAY, disable=not progress, leave=False)
