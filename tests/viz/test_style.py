"""The panels' fixed colours against the official class palettes."""

import numpy as np

from occplug.data.classes import OCC3D_COLORS, SEMANTIC_KITTI_COLORS
from occplug.viz.style import BACKGROUND, EGO_COLOR, ERROR_COLORS, FLOOR, FLOOR_LINE, MASK_HALO, MASK_LINE

CLASS_COLORS = np.array(OCC3D_COLORS + SEMANTIC_KITTI_COLORS, dtype=np.float64)  # every entry, free ones too


def _linear(rgb) -> np.ndarray:
    c = np.asarray(rgb, dtype=np.float64) / 255
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _lab(rgb) -> np.ndarray:
    """sRGB (D65) -> CIELAB."""
    xyz = _linear(rgb) @ np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]]).T
    xyz = xyz / np.array([0.95047, 1.0, 1.08883])
    f = np.where(xyz > (6 / 29) ** 3, np.cbrt(xyz), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
    return np.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], axis=-1)


def _delta_e(a, b) -> np.ndarray:
    """CIE 1976 colour difference (about 2.3 is just noticeable; 25+ is plainly another colour)."""
    return np.linalg.norm(_lab(a) - _lab(b), axis=-1)


def _contrast(a, b) -> np.ndarray:
    """WCAG 2 contrast ratio of relative luminances (1 to 21; 4.5 is the text threshold)."""
    lum_a, lum_b = _linear(a) @ [0.2126, 0.7152, 0.0722], _linear(b) @ [0.2126, 0.7152, 0.0722]
    return (np.maximum(lum_a, lum_b) + 0.05) / (np.minimum(lum_a, lum_b) + 0.05)


def test_official_palettes_keep_their_black():
    assert OCC3D_COLORS[0] == (0, 0, 0) and SEMANTIC_KITTI_COLORS[0] == (0, 0, 0)  # Occ3D others, SemanticKITTI empty


def test_every_class_colour_stands_out_from_the_background_and_the_3d_floor():
    for name, color in (("background", BACKGROUND), ("floor", FLOOR), ("floor line", FLOOR_LINE)):
        distance = _delta_e(CLASS_COLORS, color)
        assert distance.min() >= 25, (name, CLASS_COLORS[distance.argmin()], distance.min())
    assert _delta_e(CLASS_COLORS, BACKGROUND).min() >= 30
    assert _delta_e(np.array(ERROR_COLORS[1:] + (EGO_COLOR,)), BACKGROUND).min() >= 30
    assert _delta_e(FLOOR, BACKGROUND) >= 5  # the grid's floor is seen against the background


def test_the_old_slate_background_hid_occ3d_others():
    assert _delta_e(CLASS_COLORS, (28, 30, 38)).min() < 15  # why it changed: black 'others' on it


def test_mask_outline_contrasts_with_every_colour_it_is_drawn_on():
    under = np.array(
        [*CLASS_COLORS, BACKGROUND, FLOOR, *ERROR_COLORS, (255, 255, 255)], dtype=np.float64
    )  # maps, error map and the legend's white
    best = np.maximum(_contrast(under, MASK_LINE), _contrast(under, MASK_HALO))
    assert best.min() >= 4.5, under[best.argmin()]
