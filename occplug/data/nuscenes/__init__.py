"""nuScenes with Occ3D-nuScenes labels: one module per concern, imported by name (none eagerly).

* :mod:`~occplug.data.nuscenes.reader` — the data module ``occ3d_nuscenes`` (:class:`Occ3DNuScenesDataModule`).
* :mod:`~occplug.data.nuscenes.index` — ``occplug data prepare nuscenes``: the one-file index of the JSON tables.
* :mod:`~occplug.data.nuscenes.format` — Occ3D ``labels.npz`` and the ``gts/<scene>/<token>/`` layout.
* :mod:`~occplug.data.nuscenes.check` — ``occplug data check nuscenes`` / ``index``.

The class tables (Occ3D names, nuScenes category -> Occ3D id) are in :mod:`occplug.data.classes`.
"""
