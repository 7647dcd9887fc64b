"""PNG panels (matplotlib, Agg, no pyplot): the sample panel and the BEV panel.

Everything drawn is computed by the numpy/torch modules (:mod:`.bev`, :mod:`.render3d`,
:mod:`.cameras`); this module only lays the pictures out, with a legend beside every row:

* :func:`sample_figure`: BEV class maps of truth and prediction, the error map (camera-mask region
  outlined), 3D views of both, and the surround cameras in rig layout with the occupancy as a
  semi-transparent overlay and LiDAR points coloured by range. Without a prediction: the truth.
* :func:`bev_figure`: the BEV row alone (what the training callback logs).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from torch import Tensor

from occplug.geometry import GridSpec

from . import bev as B
from .cameras import blend_overlay, lidar_in_cameras, occupancy_in_cameras, rig_layout
from .deps import require_matplotlib
from .render3d import EGO_BOX, ViewCamera, default_view, render_voxels
from .style import ERROR_COLORS, ERROR_NAMES, MASK_HALO, MASK_LINE, Palette

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from occplug.data.frame import Frame

__all__ = ["bev_figure", "figure_to_rgb", "sample_figure", "save_png"]

_TEXT = "#1d1f27"
_LIDAR_CMAP = "turbo"
_LEGEND_WIDTH = 2.3  # inches
_MARGINS = {"left": 0.04, "right": 0.99, "top": 0.9, "bottom": 0.1}


def _figure(width: float, height: float, dpi: int) -> Figure:
    require_matplotlib()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=dpi, facecolor="white")
    FigureCanvasAgg(fig)
    return fig


def save_png(fig: Figure, path: str | Path) -> Path:
    """Write ``fig`` as a PNG (parent folders are created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png", facecolor=fig.get_facecolor())
    return path


def figure_to_rgb(fig: Figure) -> np.ndarray:
    """``(H, W, 3)`` uint8 pixels of a figure (for loggers with an image API)."""
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def _mask_line_style() -> dict[str, Any]:
    """How the camera-mask outline is drawn, on the maps and in their legend alike:
    :data:`~occplug.viz.style.MASK_LINE` dashes on a :data:`~occplug.viz.style.MASK_HALO` halo."""
    from matplotlib import patheffects

    halo = patheffects.withStroke(linewidth=3.0, foreground=np.asarray(MASK_HALO) / 255)
    return {"color": tuple(np.asarray(MASK_LINE) / 255), "linestyle": "--", "linewidth": 1.2, "path_effects": [halo]}


# ---------------------------------------------------------------- legends
def _class_handles(palette: Palette, ids: list[int]) -> list[Any]:
    from matplotlib.patches import Patch

    return [Patch(facecolor=palette.rgb01(i), edgecolor="#444444", linewidth=0.5, label=palette.names[i]) for i in ids]


def _legend(
    ax: Axes, palette: Palette, ids: list[int], errors: bool = False, mask: bool = False, title: str = "classes"
) -> None:
    """A legend of class colours (and error-map cases) filling ``ax``."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    ax.set_axis_off()
    handles = _class_handles(palette, ids)
    if not handles:
        handles = [Patch(facecolor="none", edgecolor="none", label="(no occupied voxels)")]
    first = ax.legend(
        handles=handles,
        loc="upper left",
        frameon=False,
        fontsize=8,
        title=title,
        title_fontproperties={"weight": "bold", "size": 9},
        handlelength=1.4,
        borderaxespad=0.0,
    )
    first._legend_box.align = "left"
    if errors or mask:
        ax.add_artist(first)
        extra = []
        if errors:
            extra += [
                Patch(
                    facecolor=np.asarray(ERROR_COLORS[c]) / 255,
                    edgecolor="#444444",
                    linewidth=0.5,
                    label=ERROR_NAMES[c],
                )
                for c in (B.CORRECT, B.WRONG_CLASS, B.MISSED, B.FALSE_OCCUPIED)
            ]
        if mask:
            extra.append(Line2D([], [], label="camera mask (outline)", **_mask_line_style()))
        second = ax.legend(
            handles=extra,
            loc="lower left",
            frameon=False,
            fontsize=8,
            title="error map" if errors else None,
            title_fontproperties={"weight": "bold", "size": 9},
            handlelength=1.4,
            borderaxespad=0.0,
        )
        second._legend_box.align = "left"


# ---------------------------------------------------------------- BEV row
def _bev_axes(ax: Axes, image: np.ndarray, grid: GridSpec, title: str, mask: Tensor | None) -> None:
    from matplotlib.patches import Rectangle

    ax.imshow(image, extent=B.image_extent(grid), interpolation="nearest", origin="upper")
    (ex0, ey0, _), (ex1, ey1, _) = EGO_BOX
    ax.add_patch(Rectangle((ey0, ex0), ey1 - ey0, ex1 - ex0, fill=False, edgecolor="white", linewidth=1.0))
    if mask is not None:
        cols = B.column_mask(mask).cpu().numpy().astype(float)
        if 0 < cols.sum() < cols.size:
            xs = grid.lower[0] + (np.arange(grid.shape[0]) + 0.5) * grid.voxel_size[0]
            ys = grid.lower[1] + (np.arange(grid.shape[1]) + 0.5) * grid.voxel_size[1]
            style = _mask_line_style()
            outline = ax.contour(
                ys,
                xs,
                cols,
                levels=[0.5],
                colors=[style["color"]],
                linewidths=style["linewidth"],
                linestyles=style["linestyle"],
            )
            outline.set_path_effects(style["path_effects"])
    ax.set_title(title, fontsize=10, color=_TEXT)
    ax.set_xlabel("y (m, left +)", fontsize=7)
    ax.set_ylabel("x (m, forward +)", fontsize=7)
    ax.tick_params(labelsize=7)


def _bev_row(
    fig: Any,
    gt: Tensor | None,
    pred: Tensor | None,
    palette: Palette,
    grid: GridSpec,
    mask: Tensor | None,
    valid: Tensor | None,
    extra: int = 0,
) -> list[Axes]:
    """BEV maps (truth, prediction, error) + legend in ``fig`` (a (sub)figure). Returns the axes,
    plus ``extra`` empty axes (after the maps, before the legend) for the caller to fill."""
    panels: list[tuple[str, np.ndarray]] = []
    if gt is not None:
        panels.append(("ground truth (BEV)", B.bev_rgb(gt, palette, valid)))
    if pred is not None:
        panels.append(("prediction (BEV)", B.bev_rgb(pred, palette, valid)))
    errors = gt is not None and pred is not None
    if errors:
        panels.append(("error map", B.error_rgb(B.error_codes(gt, pred, palette, valid))))
    n = len(panels) + extra
    widths = [1.0] * len(panels) + [1.6] * extra + [0.55]
    axes = fig.subplots(1, n + 1, gridspec_kw={"width_ratios": widths, "wspace": 0.28, **_MARGINS})
    for ax, (title, image) in zip(axes, panels, strict=False):
        _bev_axes(ax, image, grid, title, mask)
    _legend(axes[-1], palette, palette.present(gt, pred), errors=errors, mask=mask is not None)
    return list(axes[len(panels) : n])


# ---------------------------------------------------------------- 3D and cameras
def _image_axes(ax: Axes, image: np.ndarray, title: str) -> None:
    ax.imshow(image, interpolation="nearest")
    ax.set_title(title, fontsize=10, color=_TEXT)
    ax.set_axis_off()


def _camera_rows(
    fig: Any, frame: Frame, overlay: Tensor | None, overlay_name: str, palette: Palette, grid: GridSpec, alpha: float
) -> None:
    """Surround cameras in rig layout, occupancy overlay and LiDAR points, with a legend."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    names = list(frame.camera_names) or [f"camera {i}" for i in range(frame.num_cameras)]
    slots = rig_layout(names)
    rows = max(r for r, _ in slots) + 1
    h, w = frame.image_size
    classes = None
    if overlay is not None:
        classes = occupancy_in_cameras(
            overlay, grid, palette, frame.intrinsics, frame.cam_to_ego, (h, w), frame.img_aug
        )
    lidar = None
    if frame.points is not None and frame.lidar_to_ego is not None and len(frame.points):
        lidar = lidar_in_cameras(
            frame.points, frame.lidar_to_ego, frame.intrinsics, frame.cam_to_ego, (h, w), frame.img_aug
        )
        vmax = float(np.ceil(float(frame.points[:, :3].norm(dim=-1).max()) / 10.0) * 10.0)
        norm = Normalize(0.0, max(vmax, 10.0))
    outer = fig.add_gridspec(
        rows, 4, width_ratios=[1, 1, 1, 0.55], wspace=0.04, hspace=0.14, left=0.04, right=0.99, top=0.95, bottom=0.02
    )
    for c, (r, col) in enumerate(slots):
        if col >= 3:
            continue
        ax = fig.add_subplot(outer[r, col])
        image = frame.images[c]
        rgb = (
            blend_overlay(image, classes[c], palette, alpha)
            if classes is not None
            else (image.clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
        )
        ax.imshow(rgb, interpolation="nearest")
        if lidar is not None and len(lidar[c].range):
            pixel_pt = ax.get_window_extent().width / ax.figure.dpi * 72 / w
            size = max(1.0, 0.9 * pixel_pt) ** 2  # marker area, pt^2: about one image pixel wide
            ax.scatter(
                lidar[c].uv[:, 0],
                lidar[c].uv[:, 1],
                c=lidar[c].range,
                cmap=_LIDAR_CMAP,
                norm=norm,
                s=size,
                linewidths=0,
                alpha=0.9,
            )
        ax.set_xlim(-0.5, w - 0.5)
        ax.set_ylim(h - 0.5, -0.5)
        ax.set_title(names[c], fontsize=9, color=_TEXT)
        ax.set_axis_off()
    side = outer[:, 3].subgridspec(2, 1, height_ratios=[3, 1], hspace=0.3)
    lax = fig.add_subplot(side[0])
    ids = palette.present(classes) if classes is not None else []
    _legend(lax, palette, ids, title=f"overlay: {overlay_name}" if classes is not None else "no overlay")
    if lidar is not None:
        cax = fig.add_subplot(side[1])
        pos = cax.get_position()
        cax.set_position([pos.x0, pos.y0 + pos.height * 0.55, pos.width * 0.9, pos.height * 0.18])
        bar = fig.colorbar(ScalarMappable(norm=norm, cmap=colormaps[_LIDAR_CMAP]), cax=cax, orientation="horizontal")
        bar.set_label("LiDAR range (m)", fontsize=8)
        bar.ax.tick_params(labelsize=7)


# ---------------------------------------------------------------- figures
def sample_figure(
    frame: Frame,
    palette: Palette,
    grid: GridSpec,
    pred: Tensor | None = None,
    title: str | None = None,
    overlay: str = "auto",
    view: ViewCamera | None = None,
    alpha: float = 0.45,
    dpi: int = 100,
) -> Figure:
    """The panel of one sample.

    Args:
        frame: the sample (its ``voxel_labels`` are the truth; ``mask_camera`` is outlined).
        palette: class colours of the data set.
        grid: the label grid of ``frame.voxel_labels`` (and of ``pred``).
        pred: ``(X, Y, Z)`` predicted class ids, or None for the truth alone.
        title: figure title (default: token, scene and frame).
        overlay: which occupancy the cameras show: ``gt``, ``pred`` or ``auto`` (the prediction
            when there is one).
        view: the 3D view camera (default :func:`~occplug.viz.render3d.default_view`).
        alpha: opacity of the camera overlay.
        dpi: pixels per inch of the PNG.
    """
    gt = frame.voxel_labels
    if gt is None and pred is None:
        raise ValueError(f"sample {frame.token} has no voxel labels and no prediction: nothing to draw")
    if gt is not None and pred is not None and tuple(gt.shape) != tuple(pred.shape):
        raise ValueError(f"prediction grid {tuple(pred.shape)} differs from the label grid {tuple(gt.shape)}")
    if overlay not in ("auto", "gt", "pred"):
        raise ValueError(f"overlay must be auto, gt or pred, got {overlay!r}")
    valid = None if frame.voxel_invalid is None else ~frame.voxel_invalid.bool()
    both = gt is not None and pred is not None
    view = view or default_view(grid)
    h, w = frame.image_size
    rows = max(r for r, _ in rig_layout(list(frame.camera_names) or ["x"] * frame.num_cameras)) + 1
    width = 17.0
    cam_h = rows * ((width - _LEGEND_WIDTH) / 3 * h / w + 0.35)
    bev_h = 4.6
    r3d_h = ((width - _LEGEND_WIDTH) / 2 * view.height / view.width + 0.4) if both else 0.0
    title_h = 0.45
    fig = _figure(width, title_h + bev_h + r3d_h + cam_h, dpi)
    heights = [title_h, bev_h] + ([r3d_h] if both else []) + [cam_h]
    head, *subs = fig.subfigures(len(heights), 1, height_ratios=heights, hspace=0.0)
    labels_3d = (
        [("ground truth (3D)", gt), ("prediction (3D)", pred)]
        if both
        else [("ground truth (3D)" if gt is not None else "prediction (3D)", gt if gt is not None else pred)]
    )
    extra_axes = _bev_row(subs[0], gt, pred, palette, grid, frame.mask_camera, valid, extra=0 if both else 1)
    if both:
        axes = subs[1].subplots(1, 3, gridspec_kw={"width_ratios": [1, 1, 0.28], "wspace": 0.04, **_MARGINS})
        for ax, (name, labels) in zip(axes, labels_3d, strict=False):
            _image_axes(ax, render_voxels(labels, grid, palette, view, valid=valid), name)
        _legend(axes[-1], palette, palette.present(gt, pred))
    else:
        name, labels = labels_3d[0]
        _image_axes(extra_axes[0], render_voxels(labels, grid, palette, view, valid=valid), name)
    which = "pred" if (overlay == "pred" or (overlay == "auto" and pred is not None)) else "gt"
    occ = pred if which == "pred" else gt
    if occ is None:
        which, occ = ("gt", gt) if gt is not None else ("pred", pred)
    _camera_rows(subs[-1], frame, occ, "prediction" if which == "pred" else "ground truth", palette, grid, alpha)
    head.text(
        0.5,
        0.35,
        title or f"{frame.token}  (scene {frame.scene}, frame {frame.frame_index})",
        ha="center",
        va="center",
        fontsize=13,
        color=_TEXT,
        weight="bold",
    )
    return fig


def bev_figure(
    gt: Tensor | None,
    pred: Tensor | None,
    palette: Palette,
    grid: GridSpec,
    mask: Tensor | None = None,
    valid: Tensor | None = None,
    title: str | None = None,
    dpi: int = 100,
) -> Figure:
    """The BEV row alone: truth, prediction and error map (whichever exist) with their legend."""
    if gt is None and pred is None:
        raise ValueError("bev_figure needs ground truth or a prediction")
    panels = (gt is not None) + (pred is not None) + (gt is not None and pred is not None)
    fig = _figure(4.3 * panels + _LEGEND_WIDTH, 4.9, dpi)
    _bev_row(fig, gt, pred, palette, grid, mask, valid)
    if title:
        fig.suptitle(title, fontsize=11, color=_TEXT)
    return fig
