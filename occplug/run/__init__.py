"""Running a config: what ``occplug fit / validate / test / bench`` do, as functions for scripts.

* :mod:`.runner`: compose and validate a config, build its data module and model, fit, evaluate, predict, load
  checkpoints; the run directory and its records;
* :mod:`.training`: the optimiser, the learning-rate schedule and the effective batch a config asks for;
* :mod:`.phases`: a config with ``phases:`` (each phase a fit, with ``init_from``, ``freeze``, pseudo labels);
* :mod:`.weights`: ``init_from``: weights from an earlier phase, or from a state-dict file with a key map;
* :mod:`.checkpoints`: ``RunError`` and the safe checkpoint reader (both also in :mod:`.runner`);
* :mod:`.loggers`: the loggers a config names (CSV always, TensorBoard, MLflow, W&B);
* :mod:`.bench`: the cost / accuracy benchmark (``occplug bench``) and the ablation scripts' helpers.

Scripts import :mod:`.runner`, :mod:`.training` and :mod:`.bench` (``occplug.PUBLIC_MODULES``); this package's
``__init__`` imports nothing, so reading one does not load the others.
"""
