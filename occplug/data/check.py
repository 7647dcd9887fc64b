"""Read-only checks of a data tree or a prepared index, for ``occplug data check``.

Each check walks **every** sample and reports either a short summary (scenes / sequences and
samples per split, files checked) or one line: the first offending file with the number of files
affected by the same problem, e.g.::

    data/occ3d/gts/scene-0003/<token>/labels.npz: no such file (40 of 34149 label files affected)

What is checked:

* :func:`check_nuscenes` (a nuScenes tree with Occ3D labels): the JSON tables (read as ``occplug data
  prepare nuscenes`` reads them, nothing is written), the scenes of the official split (or a
  ``--splits`` file) missing from the tree, every camera image named by the tables (exists, not
  empty), every ``LIDAR_TOP`` keyframe and the ``--sweeps`` earlier sweeps (exist, whole 5-float32
  points), every lidarseg file (one byte per point of its scan), and every ``labels.npz`` (keys
  ``semantics`` / ``mask_lidar`` / ``mask_camera``, dtypes, the grid shape, class ids 0-17 or 255).
* :func:`check_index` (a prepared ``nuscenes_index.npz``): the index itself, its scenes against the
  official split (or a ``--splits`` file), and every file it names, as above (every recorded sweep).
* :func:`check_semantickitti` (``sequences/XX/``): the sequences of the standard split (train 00-07,
  09, 10; val 08) or a ``--splits`` file, present or missing; per sequence ``calib.txt`` and
  ``poses.txt``; per labelled scan the ``image_2`` image, ``voxels/*.bin|.label|.invalid|.occluded``
  (sizes of the grid), ``velodyne/*.bin`` (whole 4-float32 points) and ``labels/*.label`` (one
  ``uint32`` per point). Test sequences (11-21) are checked when present (images, velodyne).

Nothing is written anywhere; every problem raises :class:`DataCheckError` (a
:class:`~occplug.data.formats.FormatError`) with one line.
"""

from __future__ import annotations

import re
import stat
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from tqdm.auto import tqdm

from .classes import OCC3D_CLASSES
from .formats import FormatError, read_split_file
from .formats.occ3d import OCC3D_SHAPE, read_labels
from .formats.semantickitti import SSC_SHAPE, VOXEL_EXTENSIONS, voxel_file_problem
from .nuscenes_index import NuScenesIndex, collect_index, read_index, split_lists

__all__ = ["CheckSummary", "DataCheckError", "check_index", "check_nuscenes", "check_semantickitti", "read_sequence_splits"]

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


class _Findings:
    """Problems grouped by (category, kind); the first one found is reported with its count."""

    def __init__(self) -> None:
        self.checked: Counter[str] = Counter()
        self.problems: dict[tuple[str, str], list] = {}

    def check(self, category: str, n: int = 1) -> None:
        self.checked[category] += n

    def add(self, category: str, subject: str | Path, message: str, kind: str | None = None) -> None:
        """Record a problem; problems of one ``kind`` (default: the message with its numbers blanked) are counted together."""
        key = (category, kind or re.sub(r"\d+", "#", message))
        if key in self.problems:
            self.problems[key][1] += 1
        else:
            self.problems[key] = [f"{subject}: {message}", 1]

    def add_error(self, category: str, path: Path, exc: FormatError) -> None:
        """A reader's one-line error (``<path>: <problem>``) as a problem of ``path``."""
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        prefix = f"{path}: "
        self.add(category, path, text[len(prefix):] if text.startswith(prefix) else text)

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


def _progress(total: int, desc: str, progress: bool) -> tqdm:
    return tqdm(total=total, desc=desc, unit="sample", delay=PROGRESS_DELAY, disable=not progress, leave=False)


# ---------------------------------------------------------------------------------------------
# nuScenes / Occ3D


def check_nuscenes(root: str | Path, version: str, occ_root: str | Path | None = None, splits: str | Path = "official",
                   sweeps: int = 10, lidar: bool = True, shape: Sequence[int] = OCC3D_SHAPE,
                   progress: bool = True) -> CheckSummary:
    """Check a nuScenes tree (with Occ3D labels under ``occ_root``) without writing anything.

    Args:
        root: the nuScenes data root (``samples/``, ``sweeps/``, ``<version>/``).
        version: the folder of JSON tables (``v1.0-trainval``, ``v1.0-mini``, ...).
        occ_root: the Occ3D folder holding ``gts/``, or None (labels not checked).
        splits: ``official`` or a JSON file ``{split: [scene names]}`` (as ``prepare``).
        sweeps: earlier LiDAR sweeps checked per sample (as ``prepare --sweeps``).
        lidar: check LiDAR files (False for a camera-only tree).
        shape: the ``(X, Y, Z)`` every ``labels.npz`` must have.
        progress: show a progress bar on large trees.

    Raises:
        DataCheckError: one line (see the module docstring); FormatError: unreadable tables.
    """
    index = collect_index(root, version, occ_root, splits, sweeps, progress=progress, progress_delay=PROGRESS_DELAY)
    lists, where = split_lists(version, splits)
    findings = _Findings()
    scene_file = Path(root) / version / "scene.json"
    present = {split: set(names) for split, names in index.meta["splits"].items()}
    for split in sorted(lists):
        for name in sorted(lists[split]):
            findings.check(f"scenes of {where}")
            if name not in present.get(split, ()):
                findings.add(f"scenes of {where}", scene_file, f"scene {name} of the {split} split is missing", "missing")
    splits_seen, checked, notes = _check_index_files(index, Path(root), None if occ_root is None else Path(occ_root),
                                                     shape, lidar, findings, progress)
    findings.raise_first()
    return CheckSummary(f"nuScenes tree {root} ({version}; scenes per {where})", splits_seen, checked, notes)


def check_index(index: str | Path, root: str | Path | None = None, occ_root: str | Path | None = None,
                splits: str | Path = "official", lidar: bool = True, shape: Sequence[int] = OCC3D_SHAPE,
                progress: bool = True) -> CheckSummary:
    """Check a prepared index and every file it names, without writing anything.

    Args:
        index: the index file or its folder.
        root: the nuScenes root its paths are relative to (default: the one recorded in the index).
        occ_root: the Occ3D root (default: the one recorded; labels are not checked without one).
        splits: ``official`` (the lists of the index's version) or a JSON file ``{split: [scene names]}``:
            the scenes each split should hold.
        lidar: check LiDAR files (keyframes, every recorded sweep, lidarseg).
        shape: the ``(X, Y, Z)`` every ``labels.npz`` must have.
        progress: show a progress bar on large indexes.

    Raises:
        DataCheckError: one line (see the module docstring); FormatError: an unreadable index.
    """
    idx = read_index(index)
    root_dir = Path(root) if root is not None else Path(idx.meta["root"])
    if not root_dir.is_dir():
        raise DataCheckError(f"{root_dir}: no such folder (the nuScenes root the index's paths are relative to)")
    occ = occ_root if occ_root is not None else idx.meta.get("occ_root")
    occ_dir = Path(occ) if occ is not None else None
    if occ_dir is not None and not occ_dir.is_dir():
        raise DataCheckError(f"{occ_dir}: no such Occ3D folder")
    lists, where = split_lists(idx.meta.get("version", ""), splits)
    findings = _Findings()
    indexed = {name: split for split, names in idx.meta["splits"].items() for name in names}
    for split in sorted(lists):
        for name in sorted(lists[split]):
            findings.check(f"scenes of {where}")
            if name not in indexed:
                findings.add(f"scenes of {where}", idx.path, f"scene {name} of the {split} split is missing", "missing")
            elif indexed[name] != split:
                findings.add(f"scenes of {where}", idx.path, f"scene {name} is in the {indexed[name]} split, not {split}",
                             "wrong split")
    splits_seen, checked, notes = _check_index_files(idx, root_dir, occ_dir, shape, lidar, findings, progress)
    findings.raise_first()
    return CheckSummary(f"index {idx.path} (root {root_dir}; scenes per {where})", splits_seen, checked, notes)


def _check_index_files(index: NuScenesIndex, root: Path, occ_root: Path | None, shape: Sequence[int], lidar: bool,
                       findings: _Findings, progress: bool) -> tuple[dict[str, tuple[int, int]], dict[str, int], list[str]]:
    """Every file of every sample of ``index`` (see the module docstring); problems go to ``findings``.

    Returns:
        ``{split: (scenes, samples)}``, ``{kind of file: count checked}`` and notes.
    """
    shape = tuple(int(v) for v in shape)
    seen_lidar: set[Path] = set()
    num_classes = len(OCC3D_CLASSES)
    with _progress(len(index.samples), "data check", progress) as bar:
        for rec in index.samples:
            for rel in rec["cams"]:
                findings.stat("images", root / rel)
            if lidar:
                lidar_path = root / rec["lidar"]
                points = None
                for i, path in enumerate([lidar_path, *(root / r for r in rec["sweeps"])]):
                    if path in seen_lidar:
                        continue
                    seen_lidar.add(path)
                    size = findings.stat("LiDAR files", path)
                    if size is not None and size % _PCD_POINT:
                        findings.add("LiDAR files", path, f"{size} bytes is not a whole number of 5-float32 points (corrupt .bin?)")
                    elif size is not None and i == 0:
                        points = size // _PCD_POINT
                if rec.get("lidarseg"):
                    seg = root / rec["lidarseg"]
                    size = findings.stat("lidarseg files", seg)
                    if size is not None and points is not None and size != points:
                        findings.add("lidarseg files", seg, f"{size} labels for the {points} points of its LiDAR file")
            if occ_root is not None and rec.get("occ"):
                path = occ_root / rec["occ"]
                findings.check("label files")
                try:
                    labels = read_labels(path, expected_shape=shape)
                except FormatError as exc:
                    findings.add_error("label files", path, exc)
                else:
                    sem = labels.semantics
                    bad = sem[(sem >= num_classes) & (sem != 255)]
                    if bad.numel():
                        findings.add("label files", path, f"'semantics' holds class id {int(bad.max())}; expected "
                                                          f"0..{num_classes - 1} (or 255, ignored)")
            bar.update()
    splits: dict[str, tuple[int, int]] = {}
    for split in ("train", "val", "test"):
        items = index.split_indices(split)
        if items:
            splits[split] = (len({index.samples[i]["scene"] for i in items}), len(items))
    checked = {"images": findings.checked["images"], "LiDAR files (keyframes and sweeps)": findings.checked["LiDAR files"],
               "lidarseg files": findings.checked["lidarseg files"], f"label files {shape}": findings.checked["label files"]}
    notes = []
    if not lidar:
        notes.append("LiDAR files not checked (--no-lidar)")
    if occ_root is None:
        notes.append("Occ3D labels not checked (no Occ3D folder given)")
    return splits, checked, notes


# ---------------------------------------------------------------------------------------------
# SemanticKITTI


def read_sequence_splits(path: str | Path) -> dict[str, tuple[str, ...]]:
    """A JSON file ``{split: [sequence names]}`` (splits ``train``, ``val``, ``test``) replacing the standard split.

    Raises:
        FormatError: a missing or malformed file (one line naming it).
    """
    data = read_split_file(path, "sequences")
    return {k: tuple(f"{int(s):02d}" if s.isdigit() else s for s in v) for k, v in data.items()}


def check_semantickitti(root: str | Path, splits: str | Path | None = None, lidar: bool = True,
                        shape: Sequence[int] = SSC_SHAPE, progress: bool = True) -> CheckSummary:
    """Check a SemanticKITTI tree (``<root>/sequences/XX/``) without writing anything.

    Args:
        root: the folder holding ``sequences/`` (SemanticKITTI's ``dataset/``).
        splits: a JSON file ``{split: [sequences]}`` replacing splits of the standard one (train 00-07,
            09, 10; val 08; test 11-21), or None.
        lidar: check ``velodyne/`` and ``labels/`` (False for a camera-only tree).
        shape: the voxel grid of the ``voxels/`` files.
        progress: show a progress bar on large trees.

    Raises:
        DataCheckError: one line (see the module docstring).
    """
    from .semantickitti import SPLIT_SEQUENCES, _Sequence

    root = Path(root)
    if not (root / "sequences").is_dir():
        raise DataCheckError(f"{root / 'sequences'}: no such folder (SemanticKITTI's dataset/ root holds sequences/)")
    expected = dict(SPLIT_SEQUENCES)
    where = "the standard split"
    if splits is not None:
        expected.update(read_sequence_splits(splits))
        where = str(splits)
    shape = tuple(int(v) for v in shape)
    findings = _Findings()
    category = f"sequences of {where}"
    sequences: list[tuple[str, _Sequence]] = []
    for split in ("train", "val", "test"):
        for name in expected.get(split, ()):
            folder = root / "sequences" / name
            if not folder.is_dir():
                if split != "test":  # test sequences are optional
                    findings.check(category)
                    findings.add(category, folder, f"no such {split} sequence folder", "missing")
                continue
            findings.check(category)
            try:
                seq = _Sequence(root, name, with_labels=split != "test")
            except FormatError as exc:
                text = str(exc).splitlines()[0]
                subject, sep, message = text.partition(": ")
                findings.add(category, subject if sep else folder, message if sep else text)
                continue
            sequences.append((split, seq))
    total = sum(len(seq.scans) for _, seq in sequences)
    counts: dict[str, list[int]] = {}
    with _progress(total, "data check", progress) as bar:
        for split, seq in sequences:
            count = counts.setdefault(split, [0, 0])
            count[0] += 1
            count[1] += len(seq.scans)
            if seq.labelled:
                _check_voxels(seq.folder / "voxels", shape, findings)
            for scan in seq.scans:
                name = f"{scan:06d}"
                findings.stat("images", seq.folder / "image_2" / f"{name}.png")
                if lidar:
                    velo = seq.folder / "velodyne" / f"{name}.bin"
                    size = findings.stat("velodyne files", velo)
                    points = None
                    if size is not None and size % _VELO_POINT:
                        findings.add("velodyne files", velo, f"{size} bytes is not a whole number of 4-float32 points (corrupt .bin?)")
                    elif size is not None:
                        points = size // _VELO_POINT
                    if seq.labelled:
                        label = seq.folder / "labels" / f"{name}.label"
                        lsize = findings.stat("point-label files", label)
                        if lsize is not None and points is not None and lsize != 4 * points:
                            findings.add("point-label files", label, f"{lsize} bytes; expected {4 * points} (one uint32 "
                                                                     f"label per point of its velodyne scan)")
                bar.update()
    findings.raise_first()
    notes = [] if lidar else ["velodyne/ and labels/ not checked (--no-lidar)"]
    absent = [s for s in expected.get("test", ()) if not (root / "sequences" / s).is_dir()]
    if absent:
        notes.append(f"test sequences not present: {', '.join(absent)} (optional)")
    checked = {"images": findings.checked["images"], f"voxel files {shape}": findings.checked["voxel files"],
               "velodyne files": findings.checked["velodyne files"], "point-label files": findings.checked["point-label files"]}
    return CheckSummary(f"SemanticKITTI tree {root} (sequences per {where})",
                        {k: (v[0], v[1]) for k, v in counts.items()}, checked, notes, unit="sequence")


def _check_voxels(folder: Path, shape: tuple[int, ...], findings: _Findings) -> None:
    """Every scan with any ``voxels/<NNNNNN>.*`` file has all four, of the grid's sizes."""
    stems = sorted({p.stem for p in _files(folder) if p.suffix in VOXEL_EXTENSIONS})
    for stem in stems:
        for ext in VOXEL_EXTENSIONS:
            path = folder / f"{stem}{ext}"
            size = findings.stat("voxel files", path)
            if size is not None:
                problem = voxel_file_problem(ext, size, shape)
                if problem:
                    findings.add("voxel files", path, problem)


def _files(folder: Path) -> Iterable[Path]:
    return (p for p in folder.iterdir() if p.is_file()) if folder.is_dir() else ()

