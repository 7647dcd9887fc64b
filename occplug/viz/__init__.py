"""Pictures of occupancy: samples, predictions, sequences and runs (``occplug viz``).

The numeric parts need only torch/numpy and are importable anywhere; drawing PNGs needs
matplotlib and the Rerun export needs rerun-sdk (both in the ``viz`` extra,
``pip install 'occplug[viz]'``; a missing one is a :class:`~occplug.viz.deps.MissingExtraError`).

Modules:

* :mod:`.style`: the data set's :class:`~occplug.viz.style.Palette` (class colours from
  :mod:`occplug.data.classes`) and the panels' fixed colours;
* :mod:`.bev`: top-down class maps and error maps (``(X, Y)`` arrays, forward up);
* :mod:`.render3d`: the 3D view, ray cast through the grid with the exact voxel traversal;
* :mod:`.cameras`: occupancy ray cast per pixel of each camera, overlays, LiDAR projection, rig layout;
* :mod:`.panels`: the matplotlib figures (sample panel, BEV panel);
* :mod:`.runs`: curves and per-class IoU bars of a run directory;
* :mod:`.rerun_export`: a Rerun recording of a sequence;
* :mod:`.source`: frames and predictions from a config and a checkpoint;
* :mod:`.callback`: the ``bev_panel_logger`` training callback.
"""

from __future__ import annotations

from .cameras import occupancy_in_cameras
from .deps import MissingExtraError
from .render3d import default_view, render_voxels
from .style import Palette

__all__ = ["MissingExtraError", "Palette", "default_view", "occupancy_in_cameras", "render_voxels"]
