"""``occplug data check semantickitti``: a SemanticKITTI tree (``sequences/XX/``).

:func:`check_semantickitti` checks the sequences of the standard split (train 00-07, 09, 10; val 08) or a
``--splits`` file, present or missing; per sequence ``calib.txt`` and ``poses.txt``; per labelled scan the
``image_2`` image, ``voxels/*.bin|.label|.invalid|.occluded`` (sizes of the grid), ``velodyne/*.bin`` (whole
4-float32 points) and ``labels/*.label`` (one ``uint32`` per point). Test sequences (11-21) are checked when
present (images, velodyne). The grid is ``shape`` when given, else the tree's own record
(:data:`occplug.data.check.GRID_RECORD`, written by ``occplug data synth``), else SemanticKITTI's SSC grid
(``256 x 256 x 32``: the voxel files are headerless, their sizes alone do not tell a shape). Problems are
reported as :mod:`occplug.data.check` describes (one line, read only).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

from ..check import CheckSummary, DataCheckError, Findings, progress_bar, read_grid_record
from ..formats import FormatError, read_split_file
from .format import SPLIT_SEQUENCES, SSC_SHAPE, VOXEL_EXTENSIONS, voxel_file_problem
from .reader import _Sequence

__all__ = ["check_semantickitti", "read_sequence_splits"]

_VELO_POINT = 16  # bytes of a KITTI velodyne point (4 float32)


def read_sequence_splits(path: str | Path) -> dict[str, tuple[str, ...]]:
    """A JSON file ``{split: [sequence names]}`` (splits ``train``, ``val``, ``test``) replacing the standard split.

    Raises:
        FormatError: a missing or malformed file (one line naming it).
    """
    data = read_split_file(path, "sequences")
    return {k: tuple(f"{int(s):02d}" if s.isdigit() else s for s in v) for k, v in data.items()}


def check_semantickitti(root: str | Path, splits: str | Path | None = None, lidar: bool = True,
                        shape: Sequence[int] | None = None, progress: bool = True) -> CheckSummary:
    """Check a SemanticKITTI tree (``<root>/sequences/XX/``) without writing anything.

    Args:
        root: the folder holding ``sequences/`` (SemanticKITTI's ``dataset/``).
        splits: a JSON file ``{split: [sequences]}`` replacing splits of the standard one (train 00-07,
            09, 10; val 08; test 11-21), or None.
        lidar: check ``velodyne/`` and ``labels/`` (False for a camera-only tree).
        shape: the voxel grid of the ``voxels/`` files; None: the tree's grid record, else the SSC grid.
        progress: show a progress bar on large trees.

    Raises:
        DataCheckError: one line (see the module docstring).
    """
    root = Path(root)
    if not (root / "sequences").is_dir():
        raise DataCheckError(f"{root / 'sequences'}: no such folder (SemanticKITTI's dataset/ root holds sequences/)")
    expected = dict(SPLIT_SEQUENCES)
    where = "the standard split"
    if splits is not None:
        expected.update(read_sequence_splits(splits))
        where = str(splits)
    grid_note = None
    if shape is None:
        record = read_grid_record(root)
        shape = SSC_SHAPE if record is None else record[0]
        grid_note = f"grid {tuple(shape)} from {record[1]}" if record else f"grid {tuple(shape)}: SemanticKITTI's SSC grid"
    shape = tuple(int(v) for v in shape)
    findings = Findings()
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
    with progress_bar(total, "data check", progress) as bar:
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
                        findings.add(
                            "velodyne files",
                            velo,
                            f"{size} bytes is not a whole number of 4-float32 points (corrupt .bin?)",
                        )
                    elif size is not None:
                        points = size // _VELO_POINT
                    if seq.labelled:
                        label = seq.folder / "labels" / f"{name}.label"
                        lsize = findings.stat("point-label files", label)
                        if lsize is not None and points is not None and lsize != 4 * points:
                            findings.add(
                                "point-label files",
                                label,
                                f"{lsize} bytes; expected {4 * points} (one uint32 "
                                f"label per point of its velodyne scan)",
                            )
                bar.update()
    findings.raise_first()
    notes = [] if grid_note is None else [grid_note]
    if not lidar:
        notes.append("velodyne/ and labels/ not checked (--no-lidar)")
    absent = [s for s in expected.get("test", ()) if not (root / "sequences" / s).is_dir()]
    if absent:
        notes.append(f"test sequences not present: {', '.join(absent)} (optional)")
    checked = {
        "images": findings.checked["images"],
        f"voxel files {shape}": findings.checked["voxel files"],
        "velodyne files": findings.checked["velodyne files"],
        "point-label files": findings.checked["point-label files"],
    }
    return CheckSummary(
        f"SemanticKITTI tree {root} (sequences per {where})",
        {k: (v[0], v[1]) for k, v in counts.items()},
        checked,
        notes,
        unit="sequence",
    )


def _check_voxels(folder: Path, shape: tuple[int, ...], findings: Findings) -> None:
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
