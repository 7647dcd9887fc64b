"""What every ``occplug data check`` shares: the one-line error, the summary and the problem tally.

Each check (:func:`occplug.data.nuscenes.check.check_nuscenes`, :func:`~occplug.data.nuscenes.check.check_index`,
:func:`occplug.data.semantickitti.check.check_semantickitti`) walks **every** sample and reports either a short
summary (scenes / sequences and samples per split, files checked) or one line: the first offending file with the
number of files affected by the same problem, e.g.::

    data/occ3d/gts/scene-0003/<token>/labels.npz: no such file (40 of 34149 label files affected)

Nothing is written anywhere; every problem raises :class:`DataCheckError` (a
:class:`~occplug.data.formats.FormatError`) with one line.
"""

from __future__ import annotations

import re
import stat
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from tqdm.auto import tqdm

from .formats import FormatError

__all__ = ["PROGRESS_DELAY", "CheckSummary", "DataCheckError", "Findings", "progress_bar"]

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


def progress_bar(total: int, desc: str, progress: bool) -> tqdm:
    return tqdm(total=total, desc=desc, unit="sample", delay=PROGRESS_DELAY, disable=not progress, leave=False)
