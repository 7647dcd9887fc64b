"""``occplug data synth`` (write the synthetic world to disk), ``occplug data prepare`` (index a real data set),
``occplug data check`` (verify a data tree or an index, read only) and ``occplug data pseudo-labels`` (per-image
pseudo-label maps -> occplug's per-sample layout)."""

from __future__ import annotations

import argparse

from occplug.config import ConfigError
from occplug.config.validate import validate_component
from occplug.config.yamlio import parse_yaml
from occplug.plugins import get_registry

from . import paths as check
from .errors import UsageError

#: ``--format`` choices of ``data synth``: occplug's own frame files, or a real data set's layout.
SYNTH_FORMATS = ("frames", "occ3d", "semantickitti")


def add_parsers(sub: argparse._SubParsersAction) -> None:
    data = sub.add_parser("data", help="data sets")
    actions = data.add_subparsers(dest="data_command", required=True, metavar="ACTION")
    synth = actions.add_parser("synth", help="write the synthetic world to disk")
    synth.add_argument("--out", required=True, metavar="DIR")
    synth.add_argument("--preset", default="default", help="world preset (tiny, default, occ3d)")
    synth.add_argument("--splits", nargs="+", default=["train", "val", "test"], help="splits to write")
    synth.add_argument(
        "--format",
        default="frames",
        choices=SYNTH_FORMATS,
        help="frames: occplug .pt frames (default); occ3d: a nuScenes-shaped tree with Occ3D gts/; "
        "semantickitti: a SemanticKITTI-shaped tree (a grid=... knob is then in the LiDAR frame; default the SSC grid)",
    )
    synth.add_argument(
        "--pseudo",
        default=None,
        metavar="REALISM",
        help="also write pseudo labels (occ3d / semantickitti formats): perfect, default or noisy",
    )
    synth.add_argument(
        "--version", default="v1.0-trainval", help="table folder name of the occ3d format (v1.0-trainval, v1.0-mini)"
    )
    synth.add_argument("knobs", nargs="*", metavar="key=value", help="synthetic data-module arguments, e.g. seed=3")
    synth.set_defaults(func=cmd_synth)
    add_stats_parser(actions)

    prepare = actions.add_parser("prepare", help="index a real data set once, so training never walks its tables")
    datasets = prepare.add_subparsers(dest="dataset", required=True, metavar="DATASET")
    ns = datasets.add_parser("nuscenes", help="nuScenes (+ Occ3D-nuScenes labels) -> <out>/nuscenes_index.npz")
    ns.add_argument("--root", required=True, metavar="DIR", help="nuScenes data root (samples/, sweeps/, <version>/)")
    ns.add_argument(
        "--version", required=True, help="v1.0-trainval, v1.0-mini or v1.0-test (the folder of JSON tables)"
    )
    ns.add_argument("--occ", metavar="DIR", help="Occ3D-nuScenes folder holding gts/<scene>/<token>/labels.npz")
    ns.add_argument("--out", required=True, metavar="DIR", help="folder to write nuscenes_index.npz into")
    ns.add_argument(
        "--splits",
        default="official",
        metavar="official|FILE",
        help="scene split: the official lists, or a JSON file {split: [scene names]}",
    )
    ns.add_argument("--sweeps", type=int, default=10, help="earlier LiDAR sweeps to record per sample (default 10)")
    ns.add_argument("--no-check-files", action="store_true", help="do not check that every referenced file exists")
    ns.set_defaults(func=cmd_prepare_nuscenes)

    check = actions.add_parser(
        "check",
        help="verify a data tree or a prepared index (read only; exit 2 on any problem)",
        description="Verify every label file (keys, dtypes, shapes), the files the tables name "
        "(images, LiDAR), and the scenes / sequences of the official split. The grid every label file "
        "must have is --shape when given (a benchmark's grid), else the tree's own record (grid.json, "
        "written by occplug data synth), else the shape most label files share (nuScenes / Occ3D) or "
        "the SSC grid (SemanticKITTI). Writes nothing; reports the first offending file with the number "
        "of files affected and exits 2.",
    )
    targets = check.add_subparsers(dest="dataset", required=True, metavar="DATASET")
    cn = targets.add_parser(
        "nuscenes", help="a nuScenes tree with Occ3D-nuScenes labels (as prepare nuscenes reads it)"
    )
    cn.add_argument("--root", required=True, metavar="DIR", help="nuScenes data root (samples/, sweeps/, <version>/)")
    cn.add_argument(
        "--version", required=True, help="v1.0-trainval, v1.0-mini or v1.0-test (the folder of JSON tables)"
    )
    cn.add_argument("--occ", metavar="DIR", help="Occ3D-nuScenes folder holding gts/<scene>/<token>/labels.npz")
    cn.add_argument(
        "--splits",
        default="official",
        metavar="official|FILE",
        help="the scenes each split should hold: the official lists, or a JSON file {split: [scene names]}",
    )
    cn.add_argument(
        "--sweeps", type=int, default=10, help="earlier LiDAR sweeps checked per sample (default 10, as prepare)"
    )
    _check_common(cn, "the Occ3D folder's grid.json, else the shape most label files share")
    cn.set_defaults(func=cmd_check)
    ck = targets.add_parser("semantickitti", help="a SemanticKITTI tree (sequences/XX/)")
    ck.add_argument(
        "--root", required=True, metavar="DIR", help="the folder holding sequences/ (SemanticKITTI's dataset/)"
    )
    ck.add_argument(
        "--splits",
        metavar="FILE",
        help="a JSON file {split: [sequences]} replacing splits of the standard "
        "one (train 00-07, 09, 10; val 08; test 11-21, optional)",
    )
    _check_common(ck, "the tree's grid.json, else 256 256 32, the SSC grid")
    ck.set_defaults(func=cmd_check)
    ci = targets.add_parser("index", help="an index written by prepare nuscenes, and every file it names")
    ci.add_argument("--index", required=True, metavar="DIR", help="the index folder (or its nuscenes_index.npz)")
    ci.add_argument("--root", metavar="DIR", help="nuScenes data root (default: the one recorded in the index)")
    ci.add_argument("--occ", metavar="DIR", help="Occ3D-nuScenes folder (default: the one recorded in the index)")
    ci.add_argument(
        "--splits",
        default="official",
        metavar="official|FILE",
        help="the scenes each split should hold: the official lists, or a JSON file {split: [scene names]}",
    )
    _check_common(ci, "the Occ3D folder's grid.json, else the shape most label files share")
    ci.set_defaults(func=cmd_check)
    add_pseudo_labels_parser(actions)


def add_pseudo_labels_parser(actions: argparse._SubParsersAction) -> None:
    pseudo = actions.add_parser(
        "pseudo-labels", help="per-image depth / semantic maps (Metric3D, Grounded-SAM, ...) -> occplug's layout"
    )
    targets = pseudo.add_subparsers(dest="dataset", required=True, metavar="DATASET")
    pn = targets.add_parser(
        "nuscenes",
        help="maps named by sample_data token (or image file name) -> <out>/<kind>/<sample token>/<CAMERA>.<ext>",
        description="Take one depth and/or semantic map per camera image of every sample a prepared index reads "
        "(named <sample_data token>.npy|.png, or with --name-by stem as the image file; sub-folders are searched), "
        "check every map (dtype, shape, the image's aspect ratio, ids against --mapping) and write them as "
        "<out>/depth/<sample token>/<CAMERA>.npy|.png and <out>/semantics/<sample token>/<CAMERA>.png, which "
        "data.pseudo_labels reads. Adjacent frames (data.adjacent_offsets) are neighbouring samples, so they are "
        "covered; maps of non-key frames (sweeps) are not needed and left out. A missing map, a file named by no "
        "image, a bad map: one line naming the file, exit 2, nothing written.",
    )
    pn.add_argument("--index", required=True, metavar="DIR", help="the index folder (or its nuscenes_index.npz)")
    pn.add_argument("--root", metavar="DIR", help="nuScenes data root (default: the one recorded in the index)")
    pn.add_argument("--depth", metavar="DIR", help="folder of per-image depth maps: float .npy metres or 16-bit .png")
    pn.add_argument(
        "--semantics", metavar="DIR", help="folder of per-image semantic maps: 1-channel .png or integer .npy"
    )
    pn.add_argument(
        "--mapping",
        metavar="FILE",
        help="the semantic maps' class-mapping table (checked, ids checked against it, copied to the output), "
        "e.g. plugins/occplug_queryocc/configs/pseudo_labels/grounded_sam_occ3d.yaml",
    )
    pn.add_argument(
        "--name-by",
        default="token",
        choices=("token", "stem"),
        help="input files are named by the image's sample_data token (default) or by the image file's stem",
    )
    pn.add_argument(
        "--depth-scale", type=float, default=256.0, help="16-bit depth PNGs hold metres * this (default 256, KITTI's)"
    )
    pn.add_argument("--splits", nargs="+", metavar="SPLIT", help="write only these splits' samples (default: all)")
    pn.add_argument(
        "--link", action="store_true", help="hard-link unchanged files instead of copying (one file system)"
    )
    pn.add_argument("--out", required=True, metavar="DIR", help="output folder (absent or empty)")
    pn.add_argument("--no-progress", action="store_true", help="no progress bar")
    pn.set_defaults(func=cmd_pseudo_labels)


def _check_common(p: argparse.ArgumentParser, default_shape: str) -> None:
    p.add_argument(
        "--shape",
        type=int,
        nargs=3,
        metavar=("X", "Y", "Z"),
        help=f"the voxel grid every label file must have, e.g. 200 200 16 for Occ3D (default: {default_shape})",
    )
    p.add_argument("--no-lidar", action="store_true", help="camera-only data: do not check LiDAR files")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (shown on large trees)")


def add_stats_parser(actions: argparse._SubParsersAction) -> None:
    stats = actions.add_parser(
        "stats",
        help="voxels per class of a config's data split (the counts class_frequencies takes)",
        description="Count the voxel labels per class over a split of the config's data (frames whose voxel labels "
        "training may not use, e.g. a label fraction's unlabelled ones, are skipped) and print them per class and "
        "as one class_frequencies: [...] line to paste into a loss's config.",
    )
    stats.add_argument("-c", "--config", action="append", required=True, metavar="REF", help="config (repeat to merge)")
    stats.add_argument("--split", default="train", help="train, val or test (default: train)")
    stats.add_argument(
        "--mask", default="none", choices=["none", "camera"], help="count every voxel or camera-visible ones"
    )
    stats.add_argument("--max-frames", type=int, default=None, metavar="N", help="count at most N frames")
    stats.add_argument("overrides", nargs="*", metavar="key=value", help="dotlist overrides applied last")
    stats.set_defaults(func=cmd_stats)


def cmd_stats(args: argparse.Namespace) -> int:
    from occplug.data.stats import class_counts
    from occplug.run import runner

    if args.max_frames is not None and args.max_frames < 1:
        raise UsageError(f"--max-frames: expected a positive number of frames, got {args.max_frames}")
    cfg = runner.load_config(args.config, args.overrides)
    dm = runner.build_datamodule(cfg)
    if args.split not in ("train", "val", "test"):
        raise UsageError(f"--split: expected train, val or test, got {args.split!r}")
    names = list(dm.class_names)
    if not names:
        raise UsageError(f"data of {', '.join(args.config)}: the data module names no classes; nothing to count")
    with runner.data_errors():
        result = class_counts(dm.dataset(args.split), len(names), mask=args.mask, max_frames=args.max_frames)
    if result.frames == 0:
        raise UsageError(f"--split {args.split}: no frame with usable voxel labels ({result.skipped} skipped)")
    total = int(result.counts.sum())
    print(
        f"voxels per class, {args.split} split, {result.frames} frames ({result.skipped} without usable voxel labels "
        f"skipped), mask {args.mask}:"
    )
    for k, (name, count) in enumerate(zip(names, result.counts.tolist(), strict=True)):
        print(f"  {k:3d} {name:<24s} {count:>14d}  {100 * count / max(total, 1):6.2f} %")
    print(f"class_frequencies: [{', '.join(str(int(c)) for c in result.counts)}]")
    return 0


def cmd_synth(args: argparse.Namespace) -> int:
    from occplug.data.synthetic import write_dataset

    node: dict = {"type": "synthetic", "preset": args.preset}
    for item in args.knobs:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"'{item}': expected key=value (a synthetic data-module argument)")
        node[key] = parse_yaml(raw, f"'{item}'") if raw.strip() else None  # YAML 1.2, as config overrides
    registry = get_registry()
    validate_component(node, "data", "data", registry)
    if args.pseudo is not None and args.format == "frames":
        raise UsageError("--pseudo needs --format occ3d or semantickitti (the frames format has no pseudo-label files)")
    out = check.output_dir("--out", args.out, empty=True)
    lidar_grid = node.pop("grid", None) if args.format == "semantickitti" else None
    try:
        dm = registry.build("data", node)
        pseudo = None
        if args.pseudo is not None:
            from occplug.data.synthetic.pseudo import pseudo_realism

            pseudo = pseudo_realism(args.pseudo)
        if args.format == "frames":
            count = write_dataset(dm.world_config, out, splits=tuple(args.splits), progress=True)
            print(f"wrote {count} frames to {out}")
        elif args.format == "occ3d":
            from occplug.data.synthetic.export_occ3d import write_occ3d_nuscenes

            count = write_occ3d_nuscenes(
                dm.world_config,
                out,
                version=args.version,
                splits=tuple(args.splits),
                pseudo=pseudo,
                cache_dir=dm.cache_dir,
                progress=True,
            )
            grid = dm.world_config.grid
            print(f"wrote {count} samples as a nuScenes-shaped tree with Occ3D labels to {out}")
            print(
                f"index it with: occplug data prepare nuscenes --root {out} --version {args.version} --occ {out} "
                f"--out {out}/index --splits {out}/splits.json"
            )
            print(
                f"check it with: occplug data check nuscenes --root {out} --version {args.version} --occ {out} "
                f"--splits {out}/splits.json"
            )
            print(f"its label grid: {{range: {list(grid.range)}, voxel_size: {list(grid.voxel_size)}}}")
        else:
            from occplug.data.synthetic.export_semantickitti import lidar_grid as grid_of
            from occplug.data.synthetic.export_semantickitti import semantickitti_world, write_semantickitti

            world = semantickitti_world(dm.world_config, lidar_grid)
            names = write_semantickitti(
                world, out, splits=tuple(args.splits), pseudo=pseudo, cache_dir=dm.cache_dir, progress=True
            )
            grid = grid_of(world)
            print(f"wrote {sum(len(v) for v in names.values())} sequences as a SemanticKITTI-shaped tree to {out}")
            print(
                f"read it with data: {{type: semantickitti, root: {out}, splits: {names}, "
                f"grid: {{range: {list(grid.range)}, voxel_size: {list(grid.voxel_size)}}}}}"
            )
            print(f"check it with: occplug data check semantickitti --root {out} --splits {out}/splits.json")
    except (ValueError, FileNotFoundError) as exc:
        raise UsageError(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None
    return 0


def cmd_prepare_nuscenes(args: argparse.Namespace) -> int:
    from occplug.data.nuscenes.index import build_index, read_index

    if args.sweeps < 0:
        raise UsageError(f"--sweeps must be >= 0, got {args.sweeps}")
    _check_inputs(args)
    check.output_dir("--out", args.out)
    try:
        path = build_index(
            args.root,
            args.version,
            args.out,
            occ_root=args.occ,
            splits=args.splits,
            sweeps=args.sweeps,
            check_files=not args.no_check_files,
            progress=True,
        )
        index = read_index(path)
    except (ValueError, FileNotFoundError) as exc:
        raise UsageError(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None
    counts = {s: len(index.split_indices(s)) for s in ("train", "val", "test")}
    summary = ", ".join(f"{k} {v}" for k, v in counts.items() if v)
    print(f"wrote the index of {len(index.samples)} samples ({summary}) to {path}")
    return 0


def _check_inputs(args: argparse.Namespace) -> None:
    """The data roots, ``--splits FILE`` and ``--index`` of prepare / check."""
    for flag in ("root", "occ"):
        if getattr(args, flag, None):
            check.input_dir(f"--{flag}", getattr(args, flag))
    if getattr(args, "splits", None) and args.splits != "official":
        check.input_file("--splits", args.splits)
    if getattr(args, "index", None):
        check.input_path("--index", args.index, "nuScenes index")


def cmd_check(args: argparse.Namespace) -> int:
    from occplug.data.nuscenes import check as nuscenes
    from occplug.data.semantickitti import check as semantickitti

    _check_inputs(args)
    kwargs: dict = {"lidar": not args.no_lidar, "progress": not args.no_progress}
    if args.shape is not None:
        if min(args.shape) < 1:
            raise UsageError(f"--shape must be three positive sizes, got {' '.join(map(str, args.shape))}")
        kwargs["shape"] = tuple(args.shape)
    try:
        if args.dataset == "nuscenes":
            if args.sweeps < 0:
                raise UsageError(f"--sweeps must be >= 0, got {args.sweeps}")
            summary = nuscenes.check_nuscenes(
                args.root, args.version, occ_root=args.occ, splits=args.splits, sweeps=args.sweeps, **kwargs
            )
        elif args.dataset == "semantickitti":
            summary = semantickitti.check_semantickitti(args.root, splits=args.splits, **kwargs)
        else:
            summary = nuscenes.check_index(args.index, root=args.root, occ_root=args.occ, splits=args.splits, **kwargs)
    except (ValueError, FileNotFoundError) as exc:
        raise UsageError(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None
    print("\n".join(summary.lines()))
    return 0


def cmd_pseudo_labels(args: argparse.Namespace) -> int:
    from occplug.data.nuscenes.pseudo_import import import_pseudo_labels

    if args.depth is None and args.semantics is None:
        raise UsageError("give --depth and/or --semantics, the folders of per-image maps")
    if args.mapping is not None and args.semantics is None:
        raise UsageError("--mapping: a class-mapping table goes with --semantics")
    if not args.depth_scale > 0:
        raise UsageError(f"--depth-scale: expected a positive number, got {args.depth_scale}")
    check.input_path("--index", args.index, "nuScenes index")
    for flag in ("root", "depth", "semantics"):
        if getattr(args, flag) is not None:
            check.input_dir(f"--{flag}", getattr(args, flag))
    if args.mapping is not None:
        check.input_file("--mapping", args.mapping)
    check.output_dir("--out", args.out, empty=True)
    try:
        summary = import_pseudo_labels(
            args.index,
            args.out,
            depth=args.depth,
            semantics=args.semantics,
            root=args.root,
            name_by=args.name_by,
            depth_scale=args.depth_scale,
            mapping=args.mapping,
            splits=args.splits,
            link=args.link,
            progress=not args.no_progress,
        )
    except (ValueError, FileNotFoundError) as exc:
        raise UsageError(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None
    print("\n".join(summary.lines()))
    return 0
