"""``occplug viz sample | run``: pictures of samples, predictions and runs (the ``viz`` extra)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from occplug.run import runner

from . import add_config_args
from . import paths as check
from .errors import UsageError

if TYPE_CHECKING:
    from occplug.viz.source import SampleSource


def add_parsers(sub: argparse._SubParsersAction) -> None:
    viz = sub.add_parser("viz", help="pictures: samples, predictions, runs (needs the viz extra)")
    actions = viz.add_subparsers(dest="viz_command", required=True, metavar="ACTION")
    sample = actions.add_parser(
        "sample",
        help="one PNG per sample: BEV maps, error map, 3D views, cameras with overlays and LiDAR",
        description="Draw samples of a data set (ground truth alone, or with a checkpoint's predictions).",
    )
    add_config_args(sample)
    sample.add_argument(
        "--ckpt", metavar="FILE", help="checkpoint whose predictions to draw (its config is used without -c)"
    )
    sample.add_argument("--split", default="val", help="train, val, test or predict (default: val)")
    sample.add_argument("--index", type=int, nargs="+", default=[0], metavar="N", help="sample indices (default: 0)")
    sample.add_argument("--out", required=True, metavar="DIR", help="folder for the PNGs (<split>_<index>.png)")
    sample.add_argument(
        "--overlay",
        choices=("auto", "gt", "pred"),
        default="auto",
        help="occupancy drawn over the camera images (auto: the prediction when there is one)",
    )
    sample.add_argument(
        "--rerun", metavar="FILE.rrd", help="also write a Rerun recording of the whole sequence (scene) of each --index"
    )
    sample.add_argument(
        "--max-frames",
        type=int,
        metavar="N",
        help="record at most N frames of each scene in --rerun: the N from the --index frame on "
        "(fewer left in the scene: its last N); default: the whole scene",
    )
    sample.add_argument("--dpi", type=int, default=100, help="resolution of the PNGs (default: 100)")
    sample.add_argument(
        "--view-size", default="640x400", metavar="WxH", help="3D view size in pixels (default: 640x400)"
    )
    sample.set_defaults(func=cmd_sample)
    run = actions.add_parser("run", help="training/validation curves and per-class IoU bars of a run directory")
    run.add_argument("run_dir", metavar="RUN_DIR")
    run.add_argument("--out", metavar="DIR", help="where to write curves.png and class_iou.png (default: RUN_DIR)")
    run.set_defaults(func=cmd_run)


def _view_size(text: str) -> tuple[int, int]:
    """``"640x400"`` -> ``(640, 400)``."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UsageError(f"--view-size {text}: expected WIDTHxHEIGHT in pixels, e.g. 640x400") from None
    if width < 8 or height < 8:
        raise UsageError(f"--view-size {text}: at least 8x8 pixels")
    return width, height


def _rerun_paths(base: Path, scenes: list[str]) -> dict[str, Path]:
    """One file per scene: ``base`` itself for one scene, ``<stem>_<scene><suffix>`` for several."""
    if len(scenes) == 1:
        return {scenes[0]: base}
    safe = {s: "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in s) for s in scenes}
    return {s: base.with_name(f"{base.stem}_{safe[s]}{base.suffix or '.rrd'}") for s in scenes}


def cmd_sample(args: argparse.Namespace) -> int:
    from occplug.viz.deps import MissingExtraError
    from occplug.viz.source import SampleSource, SourceError

    if not args.config and not args.ckpt:
        raise UsageError("viz sample needs -c CONFIG (ground truth) and/or --ckpt CKPT (predictions)")
    check.config_refs(args.config)
    if args.ckpt:
        check.input_file("--ckpt", args.ckpt)
    check.output_dir("--out", args.out)
    if args.rerun:
        check.output_file("--rerun", args.rerun)
    if args.rerun and not str(args.rerun).endswith(".rrd"):
        raise UsageError(f"--rerun {args.rerun}: the recording file must end in .rrd")
    if args.max_frames is not None and (args.max_frames < 1 or not args.rerun):
        raise UsageError(f"--max-frames {args.max_frames}: a positive frame count, with --rerun FILE.rrd")
    view_size = _view_size(args.view_size)
    try:
        from occplug.viz.deps import require_matplotlib
        from occplug.viz.panels import sample_figure, save_png
        from occplug.viz.render3d import default_view

        require_matplotlib("occplug viz")
        ckpt = Path(args.ckpt) if args.ckpt else None
        cfg = runner.resolve_run_config(args.config, args.overrides, ckpt)
        source = SampleSource(cfg, args.split, ckpt)
        view = default_view(source.grid, *view_size)
        out = Path(args.out)
        for index in args.index:
            frame = source.frame(index)
            pred = source.predict(frame)
            title = f"{frame.token}  ({args.split} #{index}, scene {frame.scene}, frame {frame.frame_index})"
            title += f"  —  checkpoint {ckpt.name}" if ckpt else "  —  ground truth"
            fig = sample_figure(
                frame,
                source.palette,
                source.grid,
                pred=pred,
                title=title,
                overlay=args.overlay,
                dpi=args.dpi,
                view=view,
            )
            path = save_png(fig, out / f"{args.split}_{index % len(source):05d}.png")
            print(f"wrote {path}  ({frame.token})")
        if args.rerun:
            _write_rerun(source, args.index, Path(args.rerun), args.max_frames)
    except (runner.RunError, SourceError, MissingExtraError) as exc:
        raise UsageError(str(exc)) from None
    except ValueError as exc:  # e.g. a prediction on another grid, a sample with nothing to draw
        raise UsageError(str(exc).splitlines()[0]) from None
    return 0


def _window(items: list[int], index: int, max_frames: int | None) -> list[int]:
    """The frames of a scene to record: all, or ``max_frames`` of them from ``index`` on (the last
    ``max_frames`` when fewer follow it)."""
    if max_frames is None or len(items) <= max_frames:
        return items
    start = min(items.index(index), len(items) - max_frames)
    return items[start : start + max_frames]


def _write_rerun(source: SampleSource, indices: list[int], base: Path, max_frames: int | None = None) -> None:
    """One recording per scene of ``indices``, streamed frame by frame (load, predict, log, drop)."""
    from occplug.viz.rerun_export import export_sequence

    sequences: dict[str, list[int]] = {}
    for index in indices:
        scene = source.frame(index).scene
        if scene not in sequences:
            sequences[scene] = _window(source.sequence(index), index % len(source), max_frames)
    for scene, path in _rerun_paths(base, list(sequences)).items():
        items = sequences[scene]
        export_sequence(source.stream(items), path, source.grid, source.palette, predict=source.predict)
        print(f"wrote {path}  (scene {scene}, {len(items)} frames)")


def cmd_run(args: argparse.Namespace) -> int:
    from occplug.viz.deps import MissingExtraError
    from occplug.viz.runs import plot_run

    run_dir = check.input_dir("RUN_DIR", args.run_dir, missing="no such run directory")
    if args.out:
        check.output_dir("--out", args.out)
    try:
        for path in plot_run(run_dir, args.out):
            print(f"wrote {path}")
    except (FileNotFoundError, MissingExtraError) as exc:
        raise UsageError(str(exc)) from None
    return 0
