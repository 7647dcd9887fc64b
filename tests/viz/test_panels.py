"""The matplotlib panels: layout, legends with class names, PNG output."""

import numpy as np
import pytest
import torch
from viz_helpers import CAR, TRUCK

pytest.importorskip("matplotlib")

from occplug.viz.panels import bev_figure, figure_to_rgb, sample_figure, save_png  # noqa: E402
from occplug.viz.render3d import default_view  # noqa: E402


def _texts(fig):
    out = []
    for f in [fig, *fig.subfigs]:
        for ax in f.axes:
            out.append(ax.get_title())
            for legend in [c for c in ax.get_children() if type(c).__name__ == "Legend"]:
                out += [t.get_text() for t in legend.get_texts()]
        out += [t.get_text() for t in f.texts]
    return out


def test_sample_panel_ground_truth_only(tiny_dm, tiny_frame, palette, tmp_path):
    fig = sample_figure(tiny_frame, palette, tiny_dm.grid, view=default_view(tiny_dm.grid, 160, 100), dpi=50)
    texts = _texts(fig)
    for title in ("ground truth (BEV)", "ground truth (3D)", "CAM_FRONT", "CAM_BACK_RIGHT"):
        assert title in texts
    assert "prediction (BEV)" not in texts and "error map" not in texts
    present = palette.present(tiny_frame.voxel_labels)
    assert all(palette.names[i] in texts for i in present)  # the class legend names every class drawn
    path = save_png(fig, tmp_path / "a" / "panel.png")
    assert path.stat().st_size > 10_000 and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_sample_panel_with_prediction_has_error_map_and_legends(tiny_dm, tiny_frame, palette):
    pred = tiny_frame.voxel_labels.clone()
    pred[pred == CAR] = TRUCK
    view = default_view(tiny_dm.grid, 160, 100)
    fig = sample_figure(tiny_frame, palette, tiny_dm.grid, pred=pred, title="a title", view=view, dpi=50)
    texts = _texts(fig)
    for title in (
        "ground truth (BEV)",
        "prediction (BEV)",
        "error map",
        "ground truth (3D)",
        "prediction (3D)",
        "a title",
    ):
        assert title in texts
    for case in ("correct", "wrong class", "missed", "false occupied", "camera mask (outline)", "truck"):
        assert case in texts
    rgb = figure_to_rgb(fig)
    assert rgb.ndim == 3 and rgb.shape[2] == 3 and rgb.std() > 10


def test_sample_panel_rejects_mismatched_prediction(tiny_dm, tiny_frame, palette):
    with pytest.raises(ValueError, match="differs from the label grid"):
        sample_figure(tiny_frame, palette, tiny_dm.grid, pred=torch.zeros(3, 3, 3, dtype=torch.long))


def test_bev_figure_shows_the_maps_pixel_exact(grid, palette):
    from viz_helpers import empty

    gt = empty(grid)
    gt[2:6, 2:6, 0] = CAR
    fig = bev_figure(gt, gt.clone(), palette, grid, title="t")
    texts = _texts(fig)
    assert {"ground truth (BEV)", "prediction (BEV)", "error map", "car"} <= set(texts)
    ax = fig.axes[0]
    image = ax.get_images()[0].get_array()
    assert np.asarray(image).shape == (*grid.shape[:2], 3)


def test_mask_outline_and_its_legend_entry_are_drawn_alike(grid, palette):
    from matplotlib.colors import to_rgb
    from matplotlib.contour import ContourSet
    from viz_helpers import empty

    from occplug.viz.style import MASK_HALO, MASK_LINE

    gt = empty(grid)
    gt[2:6, 2:6, 0] = CAR
    mask = torch.zeros(grid.shape, dtype=torch.bool)
    mask[8:, 4:12] = True
    fig = bev_figure(gt, gt.clone(), palette, grid, mask=mask)
    contours = [c for ax in fig.axes for c in ax.collections if isinstance(c, ContourSet)]
    assert len(contours) == 3  # one outline per map
    legends = [c for ax in fig.axes for c in ax.get_children() if type(c).__name__ == "Legend"]
    entries = [
        h
        for legend in legends
        for h, t in zip(legend.legend_handles, legend.get_texts(), strict=True)
        if t.get_text() == "camera mask (outline)"
    ]
    assert len(entries) == 1
    line, halo = np.asarray(MASK_LINE) / 255, np.asarray(MASK_HALO) / 255
    assert np.allclose(to_rgb(entries[0].get_color()), line)
    for c in contours:
        assert np.allclose(c.get_edgecolor()[0][:3], line)
    for artist in [entries[0], *contours]:
        (effect,) = artist.get_path_effects()
        assert np.allclose(to_rgb(effect._gc["foreground"]), halo)
