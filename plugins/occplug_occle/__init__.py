"""occplug-occle: OccLE (label-efficient occupancy with decoupled semantic and geometric branches) as occplug
components.

Loaded through the ``occplug`` entry point ``occle = occplug_occle.plugin``, exactly as a third-party plugin; it
imports only occplug's public API. The components are in ``plugin.py``; the tested building blocks in
``geometry_branch``, ``mamba``, ``selective_scan``, ``serialization``, ``projection``, ``unets`` and ``losses``.
"""
