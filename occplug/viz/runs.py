"""Pictures of a run directory: training/validation curves and per-class IoU bars.

A run directory (see :mod:`occplug.run.runner`) holds ``logs/version_<n>/metrics.csv`` (Lightning's
CSV log; every ``--resume`` adds a version, continuing the global step) and ``metrics.json`` (the
final validation metrics, flat: ``{"mIoU": ..., "IoU_car": ..., ...}``).

* :func:`read_logs` reads every version's CSV into columns of float arrays (empty cells: NaN).
* :func:`curves_figure` plots losses, validation metrics and learning rates against the step,
  one line per metric across all versions, resumes marked.
* :func:`class_iou_figure` draws the per-class values of ``metrics.json`` as bars in the classes'
  colours, one chart per key family ``<metric>_<class>``: ``IoU_<class>`` (metrics
  ``occ3d_miou`` and ``ssc``) and ``RayIoU_<class>`` (``rayiou``). RayIoU's threshold keys
  (``RayIoU_1m``, ``RayIoU_2m``, ``RayIoU_4m``), its group and class-agnostic means
  (``RayIoU_dynamic``, ``RayIoU_static``, ``RayIoU_geometry``) and every ``*_excl`` mean are summaries
  over classes, not classes: they go into the headline with ``mIoU``, ``IoU``, ``RayIoU``,
  ``Precision``, ``Recall``.
"""

from __future__ import annotations

import csv
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from occplug.data.classes import (
    OCC3D_CLASSES,
    OCC3D_COLORS,
    SEMANTIC_KITTI_CLASSES,
    SEMANTIC_KITTI_COLORS,
    class_colors,
)

from .deps import require_matplotlib

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["RunLogs", "class_iou_figure", "curves_figure", "plot_run", "read_logs", "read_metrics"]

_VERSION = re.compile(r"version_(\d+)$")
#: The suffix of a per-threshold summary key (``RayIoU_1m``, ``RayIoU_0.5m``: ``f"{tau:g}m"``).
_THRESHOLD = re.compile(r"\d+(\.\d*)?(e[+-]?\d+)?m")
#: The suffix of a RayIoU summary over a class group or over all classes (``RayIoU_dynamic``,
#: ``RayIoU_geometry``, ``RayIoU_excl``, ``RayIoU_static_excl``: see :mod:`occplug.metrics.rayiou`).
_GROUP_SUMMARY = re.compile(r"(dynamic|static|geometry)(_excl)?|excl")
#: Bookkeeping entries of ``metrics.json``, neither metrics nor classes.
_BOOKKEEPING = ("epoch", "global_step")


@dataclass
class RunLogs:
    """The CSV logs of a run, all versions concatenated in version order.

    Attributes:
        columns: name -> ``(R,)`` float64 values over all rows (NaN where a row has none).
        version: ``(R,)`` int64 version of each row.
        versions: the version numbers found, ascending.
    """

    columns: dict[str, np.ndarray]
    version: np.ndarray
    versions: list[int]

    def series(self, name: str, x: str = "step") -> tuple[np.ndarray, np.ndarray]:
        """``(x, y)`` of the rows where ``name`` has a value."""
        y = self.columns[name]
        keep = ~np.isnan(y)
        return self.columns[x][keep], y[keep]

    def resume_steps(self) -> list[tuple[int, float]]:
        """``(version, first step)`` of every version after the first."""
        out = []
        for v in self.versions[1:]:
            steps = self.columns["step"][self.version == v]
            steps = steps[~np.isnan(steps)]
            if steps.size:
                out.append((v, float(steps.min())))
        return out


def _to_float(text: str) -> float:
    try:
        return float(text) if text.strip() else math.nan
    except ValueError:
        return math.nan


def read_logs(run_dir: str | Path) -> RunLogs:
    """Read ``<run_dir>/logs/version_*/metrics.csv`` (or a folder of ``version_*`` directly).

    Raises:
        FileNotFoundError: no CSV log there.
    """
    run_dir = Path(run_dir)
    roots = [run_dir / "logs", run_dir]
    files: list[tuple[int, Path]] = []
    for root in roots:
        for path in root.glob("version_*/metrics.csv"):
            m = _VERSION.search(path.parent.name)
            if m:
                files.append((int(m.group(1)), path))
        if files:
            break
    if not files:
        raise FileNotFoundError(f"no CSV logs (logs/version_<n>/metrics.csv) under {run_dir}")
    files.sort()
    rows: list[dict[str, str]] = []
    versions: list[int] = []
    for v, path in files:
        with path.open(newline="") as fh:
            for row in csv.DictReader(fh):
                rows.append(row)
                versions.append(v)
    names = list(dict.fromkeys(k for row in rows for k in row if k))
    columns = {n: np.array([_to_float(row.get(n) or "") for row in rows], dtype=np.float64) for n in names}
    if "step" not in columns:
        columns["step"] = np.arange(len(rows), dtype=np.float64)
    return RunLogs(columns, np.asarray(versions, dtype=np.int64), [v for v, _ in files])


def read_metrics(run_dir: str | Path) -> dict[str, float]:
    """``metrics.json`` of a run (numbers only); FileNotFoundError if absent."""
    path = Path(run_dir) / "metrics.json"
    data = json.loads(path.read_text())
    return {k: float(v) for k, v in data.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}


def _figure(width: float, height: float) -> Figure:
    require_matplotlib()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=100, facecolor="white")
    FigureCanvasAgg(fig)
    return fig


def _groups(logs: RunLogs) -> list[tuple[str, list[str]]]:
    """Plot groups: losses (every ``train/`` value is a loss term of the model, plus ``*loss``),
    headline validation metrics, learning rates; per-class columns (``IoU_car``) are left out."""
    names = [n for n in logs.columns if n not in ("step", "epoch") and np.isfinite(logs.columns[n]).any()]
    lrs = [n for n in names if n.split("/")[-1].startswith("lr") or n.endswith("learning_rate")]
    losses = [n for n in names if n not in lrs and (n.startswith("train/") or "loss" in n.split("/")[-1])]
    metrics = [n for n in names if n not in losses and n not in lrs and _per_class(n.split("/")[-1]) is None]
    groups = [("losses", losses), ("validation metrics", metrics), ("learning rate", lrs)]
    return [(t, g) for t, g in groups if g]


def curves_figure(logs: RunLogs, title: str = "") -> Figure:
    """Training and validation curves against the global step, all log versions, resumes marked."""
    groups = _groups(logs)
    if not groups:
        raise ValueError("the logs hold no numeric metrics to plot")
    fig = _figure(6.5 * len(groups), 4.4)
    axes = np.atleast_1d(fig.subplots(1, len(groups), squeeze=False)).ravel()
    for ax, (name, cols) in zip(axes, groups, strict=False):
        for col in cols:
            x, y = logs.series(col)
            if x.size == 1 or col.startswith("val/"):
                ax.plot(x, y, marker="o", markersize=3.5, linewidth=1.6, label=col)
            else:
                thin = col not in ("train/loss",) and name == "losses"
                ax.plot(x, y, linewidth=0.9 if thin else 1.5, alpha=0.75 if thin else 1.0, label=col)
        for v, step in logs.resume_steps():
            ax.axvline(step, color="#888888", linestyle=":", linewidth=1.0)
            ax.annotate(
                f"resume (v{v})",
                (step, 1.0),
                xycoords=("data", "axes fraction"),
                fontsize=7,
                color="#555555",
                rotation=90,
                va="top",
                ha="right",
            )
        ax.set_title(name, fontsize=11)
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    versions = ", ".join(str(v) for v in logs.versions)
    fig.suptitle(f"{title}  (log versions {versions})".strip(), fontsize=12)
    fig.tight_layout()
    return fig


def _class_colors(names: list[str]) -> list[tuple[float, float, float]]:
    """Colours of a family's classes from the official palette that knows most of them (``car`` is
    Occ3D's blue among Occ3D classes, SemanticKITTI's among SemanticKITTI's); other names get
    distinct hues from :func:`~occplug.data.classes.class_colors`."""
    taxonomies = ((OCC3D_CLASSES, OCC3D_COLORS), (SEMANTIC_KITTI_CLASSES, SEMANTIC_KITTI_COLORS))
    known, colors = max(taxonomies, key=lambda t: sum(n in t[0] for n in names))  # ties: Occ3D
    others = class_colors(names)  # distinct hues, for names neither palette has
    out = []
    for i, name in enumerate(names):
        r, g, b = colors[known.index(name)] if name in known else others[i]
        out.append((r / 255, g / 255, b / 255))
    return out


def _per_class(key: str) -> tuple[str, str] | None:
    """``(family, class)`` of a per-class key (``IoU_car`` -> ``("IoU", "car")``, class names may
    hold ``_``), None for a summary key (``mIoU``, ``RayIoU_1m``) or bookkeeping (``global_step``)."""
    family, sep, cls = key.partition("_")
    # mIoU_dynamic / mIoU_static / RayIoU_geometry / *_excl are means over class groups: summaries, not classes
    if not (family and sep and cls) or key in _BOOKKEEPING or family == "mIoU":
        return None
    if _THRESHOLD.fullmatch(cls) or (family == "RayIoU" and _GROUP_SUMMARY.fullmatch(cls)):
        return None
    return family, cls


def _families(metrics: dict[str, float]) -> tuple[dict[str, dict[str, float]], dict[str, float]]:
    """Per-class key families ``{"IoU": {"car": 40.1, ...}, "RayIoU": {...}}`` (a family needs 2+
    classes) and the remaining summary values ``{"mIoU": ..., "RayIoU_1m": ...}`` (bookkeeping left out)."""
    fams: dict[str, dict[str, float]] = {}
    for key, value in metrics.items():
        split = _per_class(key)
        if split is not None:
            fams.setdefault(split[0], {})[split[1]] = value
    fams = {k: v for k, v in fams.items() if len(v) >= 2}
    in_family = {f"{family}_{cls}" for family, values in fams.items() for cls in values}
    summary = {k: v for k, v in metrics.items() if k not in in_family and k not in _BOOKKEEPING}
    return fams, summary


def class_iou_figure(metrics: dict[str, float], title: str = "") -> Figure:
    """Per-class bars (one chart per ``<metric>_<class>`` family), coloured by class.

    Classes whose value is NaN (absent from truth and prediction) are marked ``n/a``.
    """
    fams, summary = _families(metrics)
    if not fams:
        raise ValueError("metrics.json holds no per-class values (keys like IoU_<class>)")
    n_cls = max(len(v) for v in fams.values())
    fig = _figure(max(8.0, 0.48 * n_cls + 2.0), 4.6 * len(fams))
    axes = np.atleast_1d(fig.subplots(len(fams), 1, squeeze=False)).ravel()
    headline = {k: v for k, v in summary.items() if math.isfinite(v)}
    for ax, (family, values) in zip(axes, fams.items(), strict=True):
        names = list(values)
        vals = np.array([values[n] for n in names], dtype=np.float64)
        finite = np.isfinite(vals)
        colors = _class_colors(names)
        bars = ax.bar(
            np.arange(len(names)), np.where(finite, vals, 0.0), color=colors, edgecolor="#333333", linewidth=0.6
        )
        for i, (bar, ok) in enumerate(zip(bars, finite, strict=True)):
            label = f"{vals[i]:.1f}" if ok else "n/a"
            ax.annotate(
                label,
                (bar.get_x() + bar.get_width() / 2, bar.get_height()),
                xytext=(0, 2),
                textcoords="offset points",
                ha="center",
                va="bottom",
                fontsize=7,
            )
        mean = float(np.nanmean(vals)) if finite.any() else math.nan
        if math.isfinite(mean):
            ax.axhline(mean, color="#333333", linestyle="--", linewidth=1.0, label=f"mean over classes = {mean:.2f}")
            ax.legend(fontsize=8, loc="upper right")
        ax.set_xticks(np.arange(len(names)))
        ax.set_xticklabels(names, rotation=40, ha="right", fontsize=8)
        ax.set_ylabel(f"{family} (%)")
        top = float(np.nanmax(vals)) if finite.any() else 1.0
        ax.set_ylim(0, max(1.0, top * 1.15))
        taus = [k.partition("_")[2] for k in summary if k.partition("_")[0] == family]
        taus = [t for t in taus if _THRESHOLD.fullmatch(t)]
        ax.set_title(f"per-class {family}" + (f" (mean over {', '.join(taus)})" if taus else ""), fontsize=11)
        ax.grid(axis="y", alpha=0.3)
    text = ", ".join(f"{k} = {v:.2f}" for k, v in headline.items())
    fig.suptitle(f"{title}  {text}".strip(), fontsize=11)
    fig.tight_layout()
    return fig


def plot_run(run_dir: str | Path, out: str | Path | None = None) -> list[Path]:
    """Write ``curves.png`` (from the CSV logs) and ``class_iou.png`` (from ``metrics.json``) into
    ``out`` (default: the run directory); return the files written.

    Raises:
        FileNotFoundError: the run directory has neither CSV logs nor ``metrics.json``.
    """
    from .panels import save_png

    require_matplotlib("occplug viz run")
    run_dir = Path(run_dir)
    out = Path(out) if out is not None else run_dir
    written: list[Path] = []
    problems: list[str] = []
    try:
        logs = read_logs(run_dir)
        written.append(save_png(curves_figure(logs, title=run_dir.name), out / "curves.png"))
    except (FileNotFoundError, ValueError) as exc:
        problems.append(str(exc))
    try:
        metrics = read_metrics(run_dir)
        written.append(save_png(class_iou_figure(metrics, title=run_dir.name), out / "class_iou.png"))
    except FileNotFoundError:
        problems.append(f"no metrics.json in {run_dir}")
    except ValueError as exc:
        problems.append(f"metrics.json: {exc}")
    if not written:
        raise FileNotFoundError(f"{run_dir} is not an occplug run directory: " + "; ".join(problems))
    return written
