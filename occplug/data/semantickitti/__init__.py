"""SemanticKITTI semantic scene completion: one module per concern, imported by name (none eagerly).

* :mod:`~occplug.data.semantickitti.reader` — the data module ``semantickitti`` (:class:`SemanticKITTIDataModule`).
* :mod:`~occplug.data.semantickitti.format` — SSC voxel files (bit-packed ``.bin``, ``.invalid``, ``.occluded``,
  ``uint16`` ``.label``) and the ``sequences/XX/voxels/`` layout.
* :mod:`~occplug.data.semantickitti.check` — ``occplug data check semantickitti``.

The class tables (SSC names, the learning map) are in :mod:`occplug.data.classes`.
"""
