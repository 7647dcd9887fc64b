"""occplug-occle: OccLE (label-efficient occupancy with decoupled semantic and geometric branches, Fang et al.) as
occplug components.

Loaded through the ``occplug`` entry point ``occle = occplug_occle.plugin``, exactly as a third-party plugin; it
imports only occplug's public API (``occplug.PUBLIC_MODULES``). The same layout in every method plugin:

* ``plugin.py``: the hooks; the registry names (``occle_*``) and the classes they build;
* components by kind: ``point_encoder.py`` (``occle_lidar_voxels``), ``scene.py`` (``occle_scene``: the
  semantic and geometric branches and their fusion), ``heads.py`` (``occle_*_head``), ``supervision.py``
  (``occle_semantic``, ``occle_geometry``, ``occle_fusion``);
* ``blocks/``: ``geometry_branch`` (the cross-plane branch), ``mamba`` and ``selective_scan`` (Dual Mamba),
  ``serialization`` (Hilbert order), ``projection``, ``losses`` (its UNets and deformable attention are the
  core's, :mod:`occplug.nn`);
* ``tools/``, run as ``python -m occplug_occle.tools.<name>``: ``ablate`` (the paper's tables), ``bench``,
  ``memory``; nothing in ``plugin.py`` imports them;
* ``configs/`` (addressed as ``occle/<name>``; ``three_phase_10pct`` is Algorithm 1) and ``README.md``; the
  measurements are in the repository's ``results/occle/``, not in the package.
"""
