"""``occplug data check nuscenes`` / ``index``: a nuScenes tree with Occ3D labels, or a prepared index.

* :func:`check_nuscenes` (a nuScenes tree with Occ3D labels): the JSON tables (read as ``occplug data
  prepare nuscenes`` reads them, nothing is written), the scenes of the official split (or a
  ``--splits`` file) missing from the tree, every camera image named by the tables (exists, not
  empty), every ``LIDAR_TOP`` keyframe and the ``--sweeps`` earlier sweeps (exist, whole 5-float32
  points), every lidarseg file (one byte per point of its scan), and every ``labels.npz`` (keys
  ``semantics`` / ``mask_lidar`` / ``mask_camera``, dtypes, the grid shape, class ids 0-17 or 255).
  The grid shape is ``shape`` when given (a benchmark's, e.g. Occ3D's ``200 x 200 x 16``), else the
  Occ3D folder's own record (:data:`occplug.data.check.GRID_RECORD`, written by ``occplug data synth``),
  else the shape most label files share: the files of another shape are reported.
* :func:`check_index` (a prepared ``nuscenes_index.npz``): the index itself, its scenes against the
  official split (or a ``--splits`` file), and every file it names, as above (every recorded sweep).

Problems are reported as :mod:`occplug.data.check` describes (one line, read only).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from pathlib import Path

from .. import check as common
from ..check import CheckSummary, DataCheckError, Findings, progress_bar, read_grid_record
from ..classes import OCC3D_CLASSES
from ..formats import FormatError
from .format import read_labels
from .index import NuScenesIndex, collect_index, missing_split_scenes, read_index, split_lists

__all__ = ["check_index", "check_nuscenes"]

_PCD_POINT = 20  # bytes of a nuScenes .pcd.bin point (5 float32)


def check_nuscenes(
    root: str | Path,
    version: str,
    occ_root: str | Path | None = None,
    splits: str | Path = "official",
    sweeps: int = 10,
    lidar: bool = True,
    shape: Sequence[int] | None = None,
    progress: bool = True,
) -> CheckSummary:
    """Check a nuScenes tree (with Occ3D labels under ``occ_root``) without writing anything.

    Args:
        root: the nuScenes data root (``samples/``, ``sweeps/``, ``<version>/``).
        version: the folder of JSON tables (``v1.0-trainval``, ``v1.0-mini``, ...).
        occ_root: the Occ3D folder holding ``gts/``, or None (labels not checked).
        splits: ``official`` or a JSON file ``{split: [scene names]}`` (as ``prepare``).
        sweeps: earlier LiDAR sweeps checked per sample (as ``prepare --sweeps``).
        lidar: check LiDAR files (False for a camera-only tree).
        shape: the ``(X, Y, Z)`` every ``labels.npz`` must have; None: the Occ3D folder's grid record, else
            the shape most label files share (see the module docstring).
        progress: show a progress bar on large trees.

    Raises:
        DataCheckError: one line (see the module docstring); FormatError: unreadable tables.
    """
    index = collect_index(
        root, version, occ_root, splits, sweeps, progress=progress, progress_delay=common.PROGRESS_DELAY
    )
    lists, where = split_lists(version, splits)
    findings = Findings()
    scene_file = Path(root) / version / "scene.json"
    missing, named = missing_split_scenes(lists, index.meta["splits"])
    findings.check(f"scenes of {where}", named)
    for split, name in missing:
        findings.add(f"scenes of {where}", scene_file, f"scene {name} of the {split} split is missing", "missing")
    splits_seen, checked, notes = _check_index_files(
        index, Path(root), None if occ_root is None else Path(occ_root), shape, lidar, findings, progress
    )
    findings.raise_first()
    return CheckSummary(f"nuScenes tree {root} ({version}; scenes per {where})", splits_seen, checked, notes)


def check_index(
    index: str | Path,
    root: str | Path | None = None,
    occ_root: str | Path | None = None,
    splits: str | Path = "official",
    lidar: bool = True,
    shape: Sequence[int] | None = None,
    progress: bool = True,
) -> CheckSummary:
    """Check a prepared index and every file it names, without writing anything.

    Args:
        index: the index file or its folder.
        root: the nuScenes root its paths are relative to (default: the one recorded in the index).
        occ_root: the Occ3D root (default: the one recorded; labels are not checked without one).
        splits: ``official`` (the lists of the index's version) or a JSON file ``{split: [scene names]}``:
            the scenes each split should hold.
        lidar: check LiDAR files (keyframes, every recorded sweep, lidarseg).
        shape: the ``(X, Y, Z)`` every ``labels.npz`` must have; None: the Occ3D folder's grid record, else
            the shape most label files share (see the module docstring).
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
    findings = Findings()
    indexed = {name: split for split, names in idx.meta["splits"].items() for name in names}
    for split in sorted(lists):
        for name in sorted(lists[split]):
            findings.check(f"scenes of {where}")
            if name not in indexed:
                findings.add(f"scenes of {where}", idx.path, f"scene {name} of the {split} split is missing", "missing")
            elif indexed[name] != split:
                findings.add(
                    f"scenes of {where}",
                    idx.path,
                    f"scene {name} is in the {indexed[name]} split, not {split}",
                    "wrong split",
                )
    splits_seen, checked, notes = _check_index_files(idx, root_dir, occ_dir, shape, lidar, findings, progress)
    findings.raise_first()
    return CheckSummary(f"index {idx.path} (root {root_dir}; scenes per {where})", splits_seen, checked, notes)


def _check_index_files(
    index: NuScenesIndex,
    root: Path,
    occ_root: Path | None,
    shape: Sequence[int] | None,
    lidar: bool,
    findings: Findings,
    progress: bool,
) -> tuple[dict[str, tuple[int, int]], dict[str, int], list[str]]:
    """Every file of every sample of ``index`` (see the module docstring); problems go to ``findings``.

    Returns:
        ``{split: (scenes, samples)}``, ``{kind of file: count checked}`` and notes.
    """
    notes = []
    if shape is None and (record := read_grid_record(occ_root)) is not None:
        shape, record_path = record
        notes.append(f"grid {shape} from {record_path}")
    shape = None if shape is None else tuple(int(v) for v in shape)
    shapes: list[tuple[Path, tuple[int, ...]]] = []  # without a grid: each file's shape, compared at the end
    seen_lidar: set[Path] = set()
    num_classes = len(OCC3D_CLASSES)
    with progress_bar(len(index.samples), "data check", progress) as bar:
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
                        findings.add(
                            "LiDAR files",
                            path,
                            f"{size} bytes is not a whole number of 5-float32 points (corrupt .bin?)",
                        )
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
                    labels = read_labels(path, expected_shape=shape)  # None: any 3-D grid
                except FormatError as exc:
                    findings.add_error("label files", path, exc)
                else:
                    sem = labels.semantics
                    if shape is None:
                        shapes.append((path, tuple(sem.shape)))
                    bad = sem[(sem >= num_classes) & (sem != 255)]
                    if bad.numel():
                        findings.add(
                            "label files",
                            path,
                            f"'semantics' holds class id {int(bad.max())}; expected "
                            f"0..{num_classes - 1} (or 255, ignored)",
                        )
            bar.update()
    if shape is None and shapes:
        shape = Counter(s for _, s in shapes).most_common(1)[0][0]
        notes.append(f"grid {shape}: the shape most label files share (no --shape, no grid record)")
        for path, other in shapes:
            if other != shape:
                findings.add(
                    "label files",
                    path,
                    f"'semantics' has shape {other}; expected {shape}, the shape most label files share",
                    "shape",
                )
    splits: dict[str, tuple[int, int]] = {}
    for split in ("train", "val", "test"):
        items = index.split_indices(split)
        if items:
            splits[split] = (len({index.samples[i]["scene"] for i in items}), len(items))
    checked = {
        "images": findings.checked["images"],
        "LiDAR files (keyframes and sweeps)": findings.checked["LiDAR files"],
        "lidarseg files": findings.checked["lidarseg files"],
        f"label files {shape}": findings.checked["label files"],
    }
    if not lidar:
        notes.append("LiDAR files not checked (--no-lidar)")
    if occ_root is None:
        notes.append("Occ3D labels not checked (no Occ3D folder given)")
    return splits, checked, notes
