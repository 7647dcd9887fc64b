"""``occplug eval``: score saved predictions against ground truth on disk, without a model.

Predictions: ``--pred DIR`` holds one ``<token>.npz`` per sample with key ``pred``, the
``(X, Y, Z)`` class-id grid (what ``occplug predict`` writes; any integer dtype).

Ground truth (``--gt DIR``, layout detected):

* **Occ3D**: ``labels.npz`` (``semantics``, ``mask_lidar``, ``mask_camera``) under
  ``DIR/gts/<scene>/<token>/``, ``DIR/<scene>/<token>/`` or ``DIR/<token>/``
  (:func:`occplug.data.nuscenes.format.find_label_files`); classes 0-17, 17 = free.
* **SemanticKITTI**: ``DIR/sequences/<XX>/voxels/<NNNNNN>.label`` with ``.invalid`` beside it;
  token ``<XX>_<NNNNNN>``; raw ids remapped to the 20 SSC classes (0 = empty, 255 ignored).

RayIoU casts from per-sample LiDAR origins, as the leaderboard does: ``--index DIR`` takes them from
a prepared nuScenes index (``occplug data prepare nuscenes``: the LiDAR positions of every sample of
the token's scene in its ego frame), or ``--origins FILE.npz`` maps each token (an array name) to an
``(S, 3)`` float array of those positions, metres (``np.savez(FILE, **{token: origins})``). Without
either, every sample uses the one origin ``--origin`` (default: the nuScenes LiDAR position for
Occ3D, the sensor origin for SemanticKITTI) and a notice says the score is not the leaderboard's.

Split (``--split``, default ``val``, the benchmark's evaluation split; ``all`` scores every sample):
ground-truth samples outside it are skipped, so ``--gt`` may be the whole tree while ``--pred`` holds
what ``occplug predict`` wrote (the val split). Where each sample belongs, first source that applies:

* ``--splits FILE``: a JSON ``{split: [names]}`` as ``occplug data prepare --splits`` reads it (scene
  names for Occ3D, sequences for SemanticKITTI, replacing the named splits of the standard one);
* ``--index DIR`` (Occ3D): the split the prepared index records for each token;
* ``<gt>/splits.json`` (what ``occplug data synth`` writes beside its tree), read as ``--splits``;
* the official lists: nuScenes ``v1.0-trainval`` / ``v1.0-test`` scenes (the ``<scene>`` folder of
  the Occ3D layouts), SemanticKITTI sequences (train 00-07, 09, 10; val 08; test 11-21).

A sample whose split none of them tells (a scene in no list, the flat ``DIR/<token>/`` layout) is one
error line suggesting ``--splits`` (``--index`` for the flat layout) or ``--split all``.

Every sample is checked before anything is written: a missing or mismatched file, a ground-truth class
id outside the taxonomy (255 is the ignore label), a predicted id outside it for ``miou`` / ``ssc``
(RayIoU scores such an id as occupied with no class, as SparseOcc's scorer does) or a non-finite
RayIoU origin is one error line naming the file, the first offending token and how many samples are
affected (exit code 2). A prediction for a
ground-truth sample outside the split is ignored; one with no ground truth at all is an error.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from occplug.data.classes import OCC3D_CLASSES, OCC3D_FREE, SEMANTIC_KITTI_CLASSES
from occplug.data.formats import FormatError, find_predictions, load_npz, read_prediction
from occplug.data.frame import Batch
from occplug.data.nuscenes import format as occ3d
from occplug.data.semantickitti import format as semantickitti
from occplug.geometry import GridSpec

from . import paths as check
from .errors import UsageError

#: ``--metric`` choices: Occ3D mIoU, RayIoU, SemanticKITTI SSC.
METRICS = ("miou", "rayiou", "ssc")
#: ``--split`` choices (``all``: every ground-truth sample).
EVAL_SPLITS = ("train", "val", "test", "all")
#: The ground-truth id every metric ignores (Occ3D's and SemanticKITTI's 255); any other id must be a class.
IGNORE_LABEL = 255
#: The split record ``occplug data synth`` writes at the root of its trees (read as ``--splits`` when present).
TREE_SPLITS = "splits.json"

_DESCRIPTION = """\
predictions: --pred DIR holds <token>.npz files with key 'pred', the (X, Y, Z) class-id grid
(what occplug predict writes).

ground truth (--gt DIR, layout detected):
  Occ3D          labels.npz (semantics, mask_lidar, mask_camera) in DIR/gts/<scene>/<token>/,
                 DIR/<scene>/<token>/ or DIR/<token>/; classes 0-17, 17 = free
  SemanticKITTI  DIR/sequences/<XX>/voxels/<NNNNNN>.label + .invalid; token <XX>_<NNNNNN>;
                 raw ids remapped to the 20 SSC classes (0 = empty, 255 ignored)

RayIoU origins (the leaderboard casts from the LiDAR positions of the sample's sequence):
  --index DIR      a prepared nuScenes index (occplug data prepare nuscenes) gives them per token
  --origins FILE   .npz mapping each token to an (S, 3) float array of them, in the sample's ego
                   frame (np.savez(FILE, **{token: origins}))
  neither          every sample uses the single --origin (default: the nuScenes LiDAR position
                   for Occ3D, the sensor origin for SemanticKITTI); a notice says the score is
                   then not comparable with the leaderboard's

split (--split, default val; all = every sample): ground truth outside it is skipped, so --gt can
be the whole tree while --pred holds what occplug predict wrote (val). A sample's split comes from
the first that applies:
  --splits FILE    JSON {split: [names]} as in occplug data prepare --splits (scene names for
                   Occ3D; sequences for SemanticKITTI, replacing those splits of the standard one)
  --index DIR      (Occ3D) the split the prepared index records per token
  DIR/splits.json  the split record occplug data synth writes beside its trees (as --splits)
  official lists   nuScenes v1.0-trainval/v1.0-test scenes (the <scene> folder of the Occ3D
                   layouts); SemanticKITTI train 00-07, 09, 10, val 08, test 11-21
A sample none of them places is an error; pass --splits FILE (flat layout: --index DIR) or
--split all.

A missing or mismatched file (a missing prediction inside the split included), a ground-truth class
id outside the taxonomy (255 = ignore), a predicted id outside it for miou / ssc (rayiou scores it as
occupied with no class, as SparseOcc does) or a non-finite origin is one error line naming the file,
the first offending token and the number of samples affected (exit code 2); nothing is written then.
"""


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "eval",
        help="score saved predictions (<token>.npz) against Occ3D or SemanticKITTI ground truth",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--pred", required=True, metavar="DIR", help="folder of <token>.npz predictions (key 'pred')")
    p.add_argument("--gt", required=True, metavar="DIR", help="ground-truth root (Occ3D or SemanticKITTI layout)")
    p.add_argument(
        "--metric",
        action="extend",
        nargs="+",
        choices=METRICS,
        metavar="NAME",
        help="miou, rayiou and/or ssc (default: miou for Occ3D, ssc for SemanticKITTI)",
    )
    p.add_argument("--json", metavar="OUT", help="write the results to this JSON file")
    p.add_argument(
        "--split",
        choices=EVAL_SPLITS,
        default="val",
        help="score the ground truth of this split only (default val, the benchmark's; all: every sample)",
    )
    p.add_argument(
        "--splits",
        metavar="FILE",
        help="JSON {split: [scene names or sequences]} placing each sample (as data prepare --splits; "
        "default: DIR/splits.json if present, else the official lists)",
    )
    p.add_argument(
        "--mask",
        choices=("none", "camera", "lidar", "camera_and_lidar"),
        help="voxels miou evaluates (Occ3D default: camera)",
    )
    p.add_argument("--format", choices=("auto", "occ3d", "semantickitti"), default="auto", help="ground-truth layout")
    origins = p.add_mutually_exclusive_group()
    origins.add_argument(
        "--origins", metavar="FILE", help="RayIoU origins: .npz of token -> (S, 3) ego-frame LiDAR positions"
    )
    origins.add_argument(
        "--index", metavar="DIR", help="RayIoU origins from a prepared nuScenes index (occplug data prepare)"
    )
    p.add_argument(
        "--origin",
        nargs=3,
        type=float,
        metavar=("X", "Y", "Z"),
        help="RayIoU's single origin when --origins is not given (ego frame, metres)",
    )
    p.add_argument(
        "--grid",
        nargs=6,
        type=float,
        metavar="R",
        help="grid range x0 y0 z0 x1 y1 z1 (default: the data set's: Occ3D or SemanticKITTI SSC)",
    )
    p.add_argument("--voxel-size", nargs="+", type=float, metavar="V", help="voxel size with --grid (1 or 3 numbers)")
    p.add_argument("--device", default="cpu", help="torch device to compute on (default cpu)")
    p.set_defaults(func=cmd_eval)


@dataclass
class _Layout:
    """One ground-truth layout: where its samples are and how to read one into batch fields."""

    name: str
    files: dict[str, Path]
    read: Callable[[Path], dict[str, Tensor]]
    grid: GridSpec
    class_names: tuple[str, ...]
    free_label: int
    origin: tuple[float, float, float]
    default_metrics: tuple[str, ...]


def _grid_arg(args: argparse.Namespace) -> GridSpec | None:
    if args.grid is None:
        if args.voxel_size is not None:
            raise UsageError("--voxel-size needs --grid")
        return None
    if args.voxel_size is None or len(args.voxel_size) not in (1, 3):
        raise UsageError("--grid needs --voxel-size with 1 or 3 numbers")
    try:
        return GridSpec(args.grid, args.voxel_size[0] if len(args.voxel_size) == 1 else args.voxel_size)
    except ValueError as exc:
        raise UsageError(f"--grid: {exc}") from None


def _layout(args: argparse.Namespace) -> _Layout:
    root = Path(args.gt)
    if not root.is_dir():
        raise UsageError(f"--gt {root}: not a folder")
    fmt = args.format
    if fmt == "auto":
        fmt = "semantickitti" if (root / "sequences").is_dir() else "occ3d"
    grid = _grid_arg(args)
    try:
        if fmt == "semantickitti":
            grid = grid or semantickitti.SSC_GRID
            shape = grid.shape

            def read_kitti(path: Path) -> dict[str, Tensor]:
                vox = semantickitti.read_voxels(path, shape)
                return {"voxel_labels": vox.labels, "voxel_invalid": vox.invalid}

            return _Layout(
                "semantickitti",
                semantickitti.find_label_files(root),
                read_kitti,
                grid,
                SEMANTIC_KITTI_CLASSES,
                0,
                (0.0, 0.0, 0.0),
                ("ssc",),
            )
        expected = None if grid is None else grid.shape

        def read_occ3d(path: Path) -> dict[str, Tensor]:
            labels = occ3d.read_labels(path, expected)
            return {
                "voxel_labels": labels.semantics,
                "mask_camera": labels.mask_camera,
                "mask_lidar": labels.mask_lidar,
            }

        return _Layout(
            "occ3d",
            occ3d.find_label_files(root),
            read_occ3d,
            grid or occ3d.OCC3D_GRID,
            OCC3D_CLASSES,
            OCC3D_FREE,
            occ3d.OCC3D_LIDAR_ORIGIN,
            ("miou",),
        )
    except FormatError as exc:
        raise UsageError(str(exc)) from None


def _split_members(layout: _Layout, args: argparse.Namespace) -> tuple[dict[str, set[str] | None], str]:
    """``({token: the splits it belongs to, or None when unknown}, where the splits came from)``."""
    root = Path(args.gt)
    record = root / TREE_SPLITS
    split_file = args.splits or (str(record) if record.is_file() else None)
    try:
        if layout.name == "semantickitti":
            from occplug.data.semantickitti.check import read_sequence_splits

            lists = dict(semantickitti.SPLIT_SEQUENCES)
            if split_file is not None:
                lists.update(read_sequence_splits(split_file))
            where = split_file or "the standard SemanticKITTI split"
            return {t: {s for s, seqs in lists.items() if t.split("_")[0] in seqs} or None for t in layout.files}, where
        from occplug.data.nuscenes.index import official_splits, read_index, split_lists

        if args.splits is None and args.index:
            index = read_index(args.index)
            recorded = {rec["token"]: rec["split"] for rec in index.samples}
            return {t: {recorded[t]} if t in recorded else None for t in layout.files}, f"the index {index.path}"
        if split_file is not None:
            lists, where = split_lists("v1.0-trainval", split_file)
        else:
            lists, where = (
                {**official_splits("v1.0-trainval"), **official_splits("v1.0-test")},
                ("the official nuScenes v1.0-trainval / v1.0-test split"),
            )
    except FormatError as exc:
        raise UsageError(str(exc)) from None
    out: dict[str, set[str] | None] = {}
    for token, path in layout.files.items():
        scene_dir = path.parent.parent
        scene = None if scene_dir.resolve() == root.resolve() else scene_dir.name  # flat layout: no scene
        out[token] = {s for s, names in lists.items() if scene in names} or None
    return out, where


def _select_split(layout: _Layout, args: argparse.Namespace) -> dict[str, Path]:
    """The ground-truth files of ``--split`` (all of them for ``all``).

    Raises:
        UsageError: a sample whose split cannot be told, or no sample in the split (one line).
    """
    if args.split == "all":
        if args.splits is not None:
            raise UsageError("--splits places samples in splits; it needs --split train, val or test, not all")
        return layout.files
    members, where = _split_members(layout, args)
    unknown = [t for t, m in members.items() if m is None]
    if unknown:
        scene_dir = layout.files[unknown[0]].parent.parent
        fix = "pass --splits FILE (a JSON {split: [names]}) or --split all"
        if layout.name == "semantickitti":
            what = f"sequence {unknown[0].split('_')[0]} is in no split of {where}"
        elif scene_dir.resolve() == Path(args.gt).resolve():
            what, fix = "the flat <token>/labels.npz layout names no scene", "pass --index DIR or --split all"
        else:
            what = f"scene folder {scene_dir.name} is in no split of {where}"
        raise UsageError(
            f"--split {args.split}: cannot tell the split of token {unknown[0]} ({what}); {fix} "
            f"({len(unknown)} of {len(members)} samples affected)"
        )
    chosen = {t: p for t, p in layout.files.items() if args.split in members[t]}
    if not chosen:
        raise UsageError(
            f"--gt {args.gt}: none of its {len(members)} samples is in the {args.split} split of {where}; "
            "pick another --split (train, val, test, all) or pass --splits FILE"
        )
    return chosen


def _metrics(names: list[str], layout: _Layout, args: argparse.Namespace, device: torch.device) -> dict:
    from occplug.metrics import Occ3DMIoU, RayIoU, SSCMetrics

    common = {
        "num_classes": len(layout.class_names),
        "class_names": layout.class_names,
        "free_label": layout.free_label,
    }
    out = {}
    for name in names:
        if name == "miou":
            if layout.name != "occ3d":
                raise UsageError("--metric miou is the Occ3D metric; SemanticKITTI is scored with --metric ssc")
            out[name] = Occ3DMIoU(**common, mask=args.mask or "camera")
        elif name == "rayiou":
            out[name] = RayIoU(**common, grid=layout.grid)
        else:
            out[name] = SSCMetrics(**common, ignore_label=255)
    if args.mask is not None and "miou" not in out:
        raise UsageError("--mask applies to --metric miou only")
    return {name: metric.to(device) for name, metric in out.items()}


def _read_origins(path: Path, tokens: list[str]) -> dict[str, Tensor]:
    try:
        arrays = load_npz(path)
    except FormatError as exc:
        raise UsageError(f"--origins: {exc}") from None
    missing = [t for t in tokens if t not in arrays]
    if missing:
        raise UsageError(
            f"--origins {path}: no origins for token {missing[0]} ({len(missing)} of {len(tokens)} samples affected)"
        )
    bad = [
        t
        for t in tokens
        if arrays[t].ndim != 2 or arrays[t].shape[1] != 3 or not np.issubdtype(arrays[t].dtype, np.number)
    ]
    if bad:
        raise UsageError(
            f"--origins {path}: token {bad[0]} has an array of shape {arrays[bad[0]].shape} ({arrays[bad[0]].dtype}); "
            f"expected (S, 3) numbers ({len(bad)} of {len(tokens)} samples affected)"
        )
    return {t: torch.from_numpy(arrays[t].astype(np.float64)) for t in tokens}


def _index_origins(path: Path, tokens: list[str]) -> dict[str, Tensor]:
    from occplug.data.nuscenes.index import read_index

    try:
        index = read_index(path)
    except FormatError as exc:
        raise UsageError(f"--index: {exc}") from None
    position = {rec["token"]: i for i, rec in enumerate(index.samples)}
    missing = [t for t in tokens if t not in position]
    if missing:
        raise UsageError(
            f"--index {path}: no sample with token {missing[0]} ({len(missing)} of {len(tokens)} samples affected)"
        )
    return {t: torch.from_numpy(index.sequence_lidar_origins(position[t])) for t in tokens}


def _check_finite_origins(origins: dict[str, Tensor], source: str, samples: int) -> None:
    """Raise one line naming the first token whose RayIoU origins hold NaN or inf."""
    bad = [t for t, o in origins.items() if not bool(torch.isfinite(o).all())]
    if bad:
        row = next(r for r in origins[bad[0]] if not bool(torch.isfinite(r).all()))
        raise UsageError(
            f"{source}: token {bad[0]} has a non-finite origin ({', '.join(f'{v:g}' for v in row.tolist())}); "
            f"expected finite metres ({len(bad)} of {samples} samples affected)"
        )


def _label_problem(labels: Tensor, layout: _Layout, path: Path) -> str | None:
    """Why ``labels`` cannot be scored (a class id outside the taxonomy, the ignore label aside), or None."""
    ids = torch.unique(labels).long()
    bad = ids[((ids < 0) | (ids >= len(layout.class_names))) & (ids != IGNORE_LABEL)]
    if bad.numel():
        return (
            f"{path}: ground-truth class id {int(bad[0])} is outside the taxonomy "
            f"(0..{len(layout.class_names) - 1}, {IGNORE_LABEL} = ignore)"
        )
    return None


def _prediction_problem(pred: Tensor, metrics: dict, layout: _Layout, path: Path) -> str | None:
    """Why a confusion-matrix metric cannot score ``pred`` (an id outside the taxonomy), or None.

    RayIoU scores such ids (occupied, no class, as SparseOcc's scorer does), so RayIoU alone never refuses.
    """
    strict = [name for name in metrics if name != "rayiou"]
    if not strict or not pred.numel():
        return None
    low, high = int(pred.min()), int(pred.max())
    count = len(layout.class_names)
    if low >= 0 and high < count:
        return None
    return (
        f"{path}: predicted class id {low if low < 0 else high} is outside 0..{count - 1}, which --metric "
        f"{' and '.join(strict)} cannot score (--metric rayiou alone scores it as occupied with no class)"
    )


def _batch(token: str, fields: dict[str, Tensor], origins: Tensor, device: torch.device) -> Batch:
    """A one-sample Batch holding just what the metrics read."""
    eye3 = torch.eye(3)[None, None]
    return Batch(
        images=torch.zeros(1, 0, 3, 1, 1),
        intrinsics=eye3.expand(1, 0, 3, 3),
        cam_to_ego=torch.eye(4)[None, None].expand(1, 0, 4, 4),
        img_aug=eye3.expand(1, 0, 3, 3),
        ego_to_global=torch.eye(4, dtype=torch.float64)[None],
        timestamp=torch.zeros(1, dtype=torch.float64),
        frame_index=torch.zeros(1, dtype=torch.int64),
        has_voxel_labels=torch.ones(1, dtype=torch.bool),
        is_sequence_start=torch.ones(1, dtype=torch.bool),
        scene=[""],
        token=[token],
        sequence_lidar_origins=[origins],
        **{name: value[None] for name, value in fields.items()},
    ).to(device)


def evaluate_folder(args: argparse.Namespace) -> tuple[dict[str, dict[str, float]], dict[str, str], int]:
    """Score every sample; return ``({metric: {key: value}}, {metric: table}, samples)``.

    Raises:
        UsageError: a missing, extra or mismatched file (one line with the first token and a count).
    """
    pred_dir = Path(args.pred)
    if not pred_dir.is_dir():
        raise UsageError(f"--pred {pred_dir}: not a folder")
    try:
        device = torch.device(args.device)
        torch.empty(0, device=device)
    except (RuntimeError, AssertionError) as exc:
        raise UsageError(f"--device {args.device}: {str(exc).splitlines()[0]}") from None
    layout = _layout(args)
    if not layout.files:
        raise UsageError(
            f"--gt {args.gt}: no {layout.name} ground truth found (see occplug eval --help for the layouts)"
        )
    preds = find_predictions(pred_dir)
    everything = layout.files
    layout.files = _select_split(layout, args)
    tokens = sorted(layout.files)
    missing = [t for t in tokens if t not in preds]
    if missing:
        within = "" if args.split == "all" else f" of the {args.split} split"
        raise UsageError(
            f"no prediction for token {missing[0]}{within} ({pred_dir / (missing[0] + '.npz')}); "
            f"{len(missing)} of {len(tokens)} samples affected"
        )
    extra = sorted(set(preds) - set(everything))  # predictions of ground truth outside the split are ignored
    if extra:
        raise UsageError(
            f"prediction {preds[extra[0]]} has no ground truth in {args.gt}; {len(extra)} predictions affected"
        )
    names = list(dict.fromkeys(args.metric or layout.default_metrics))
    metrics = _metrics(names, layout, args, device)
    notices: list[str] = []
    origins = {}
    if "rayiou" in metrics:
        if args.origins:
            origins = _read_origins(Path(args.origins), tokens)
        elif args.index:
            origins = _index_origins(Path(args.index), tokens)
        else:
            notices.append(
                "notice: RayIoU casts from one fixed origin per sample; the leaderboard casts from the "
                "LiDAR positions of each sample's sequence (--index DIR or --origins FILE)"
            )
        source = f"--origins {args.origins}" if args.origins else f"--index {args.index}"
        _check_finite_origins(origins, source, len(tokens))
        single = torch.tensor([args.origin or layout.origin], dtype=torch.float64)
        origins = {t: origins.get(t, single) for t in tokens}
    first_error, errors = None, 0
    for token in _progress(tokens):
        try:
            fields = layout.read(layout.files[token])
            shape = tuple(fields["voxel_labels"].shape)
            pred = read_prediction(preds[token], shape)
        except FormatError as exc:
            first_error, errors = first_error or f"token {token}: {exc}", errors + 1
            continue
        problem = _label_problem(fields["voxel_labels"], layout, layout.files[token]) or _prediction_problem(
            pred, metrics, layout, preds[token]
        )
        if problem:
            first_error, errors = first_error or f"token {token}: {problem}", errors + 1
            continue
        if "rayiou" in metrics and shape != layout.grid.shape:
            first_error = first_error or (
                f"token {token}: labels of shape {shape} do not match the RayIoU grid's {layout.grid.shape}; pass --grid/--voxel-size"
            )
            errors += 1
        if first_error:
            continue  # only counting the affected samples from here on
        batch = _batch(token, fields, origins.get(token, torch.zeros(1, 3)), device)
        for metric in metrics.values():
            metric.update(pred[None].to(device), batch)
    if first_error:
        raise UsageError(f"{first_error} ({errors} of {len(tokens)} samples affected)")
    results = {name: {k: float(v) for k, v in metric.compute().items()} for name, metric in metrics.items()}
    tables = {name: metric.table() for name, metric in metrics.items()}
    for line in notices:  # after every check passed: an error stays the only line
        print(line, file=sys.stderr)
    return results, tables, len(tokens)


def _progress(tokens: list[str]):
    from tqdm.auto import tqdm

    return tqdm(tokens, desc="eval", unit="sample", disable=None, leave=False)


def _is_headline(key: str) -> bool:
    """Summary keys: everything except per-class values (``IoU_<class>``, ``RayIoU_<class>``); RayIoU's
    per-threshold, group, class-agnostic and ``*_excl`` means are summaries."""
    if key.startswith("IoU_"):
        return False
    summary = r"RayIoU_([0-9.]+m|(dynamic|static|geometry)(_excl)?|excl)"
    return not key.startswith("RayIoU_") or re.fullmatch(summary, key) is not None


def cmd_eval(args: argparse.Namespace) -> int:
    check.input_dir("--pred", args.pred)
    check.input_dir("--gt", args.gt)
    if args.origins:
        check.input_file("--origins", args.origins)
    if args.index:
        check.input_path("--index", args.index, "nuScenes index")
    if args.json:
        check.output_file("--json", args.json)
    if args.origin is not None and not all(math.isfinite(v) for v in args.origin):
        raise UsageError(f"--origin: expected three finite numbers (metres), got {' '.join(map(str, args.origin))}")
    results, tables, count = evaluate_folder(args)
    for table in tables.values():
        print(table)
    summary = "; ".join(
        f"{name}: " + ", ".join(f"{k}={v:.2f}" for k, v in res.items() if _is_headline(k))
        for name, res in results.items()
    )
    within = "" if args.split == "all" else f" of the {args.split} split"
    print(f"evaluated {count} samples{within} — {summary}")
    if args.json:
        payload = {
            "samples": count,
            "split": args.split,
            "gt": str(args.gt),
            "pred": str(args.pred),
            "metrics": {
                name: {k: (None if math.isnan(v) else v) for k, v in res.items()} for name, res in results.items()
            },
        }
        if "miou" in results:
            payload["eval_mask"] = args.mask or "camera"
        from occplug.run.runner import write_text_atomic

        write_text_atomic(Path(args.json), json.dumps(payload, indent=2) + "\n")
    return 0
