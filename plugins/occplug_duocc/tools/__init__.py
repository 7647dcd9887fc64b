"""DuOcc's user tools, each run as ``python -m occplug_duocc.tools.<name>``: ``ablate`` (Tab. 4 / 5), ``bench``,
``fit_anchors`` (with ``anchors``: the detector's k-means anchors), ``fit_class_weights`` (with ``class_weights``:
the public code's CE weights), ``stream_gain`` (accuracy by position in the scene), ``selection`` (what QueryAgg's
selection hands DQA) and ``detection_eval`` (the detector's mAP, which ``ablate`` reports). Nothing here is
imported by ``plugin.py``."""
