"""occplug-duocc: DuOcc (stream- and query-guided feature aggregation, Moon et al.) as occplug components.

Loaded through the ``occplug`` entry point ``duocc = occplug_duocc.plugin``, exactly as a third-party plugin; it
imports only occplug's public API (``occplug.PUBLIC_MODULES``). The same layout in every method plugin:

* ``plugin.py``: the hooks; the registry names (``duocc_*``) and the classes they build;
* components by kind: ``scene.py`` (``duocc_stream``: 3D-FPN, StreamAgg and QueryAgg over a ``StreamState``;
  ``duocc_stacking``), ``heads.py`` (``duocc_decoder``), ``supervision/`` (``auxiliary.py``: ``duocc_occupied``,
  ``duocc_forecast``, ``duocc_detection``; ``mask_decoder.py``: ``duocc_mask``);
* ``blocks/``: ``fpn3d``, ``stream_agg`` (RefineNet, fusion), ``queryagg`` (I2Q, V2Q, DQA wiring), ``dqa``,
  ``detector`` (the Sparse4D-style detector), ``image_aggregation`` (its deformable multi-camera, multi-level
  image sampling), ``boxes`` (the encoded box), ``detection_loss``, ``v2q`` (``VoxelToQuery``), ``denoising``,
  ``matching``;
* ``tools/``, run as ``python -m occplug_duocc.tools.<name>``: ``ablate`` (Tab. 4 / 5), ``bench``, ``fit_anchors``
  (+ ``anchors``), ``fit_class_weights`` (+ ``class_weights``), ``stream_gain``, ``selection``, ``detection_eval``
  (the detector's mAP); nothing in ``plugin.py`` imports them;
* ``configs/`` (addressed as ``duocc/<name>``) and ``README.md``; the measurements are in the repository's
  ``results/duocc/``, not in the package.
"""
