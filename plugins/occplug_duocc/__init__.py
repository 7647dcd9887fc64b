"""occplug-duocc: DuOcc (stream- and query-guided feature aggregation, Moon et al.) as occplug components.

Loaded through the ``occplug`` entry point ``duocc = occplug_duocc.plugin``, exactly as a third-party plugin; it
imports only occplug's public API (``occplug.PUBLIC_MODULES``). The same layout in every method plugin:

* ``plugin.py``: the hooks; the registry names (``duocc_*``) and the classes they build;
* components by kind: ``scene.py`` (``duocc_stream``: 3D-FPN, StreamAgg and QueryAgg over a ``StreamState``;
  ``duocc_stacking``), ``heads.py`` (``duocc_decoder``), ``supervision.py`` (``duocc_occupied``,
  ``duocc_forecast``, ``duocc_detection``) and ``mask_decoder.py`` (``duocc_mask``);
* building blocks: ``fpn3d``, ``stream_agg`` (RefineNet, fusion), ``queryagg`` (I2Q, V2Q, DQA wiring), ``dqa``,
  ``detector`` (the Sparse4D-style detector), ``image_aggregation`` (its deformable multi-camera, multi-level
  image sampling), ``boxes`` (the encoded box), ``detection_loss``, ``v2q`` (``VoxelToQuery``), ``denoising``,
  ``matching``, ``anchors``, ``class_weights``, ``detection_eval`` (the detector's mAP);
* scripts, run as ``python -m occplug_duocc.<name>``: ``ablate`` (Tab. 4 / 5), ``bench``, ``stream_gain``,
  ``fit_anchors``, ``fit_class_weights``, ``detector_overfit``, ``history_norm``;
* ``configs/`` (addressed as ``duocc/<name>``), ``README.md`` (how to use it) and ``RESULTS.md`` (what was
  measured).
"""
