"""QueryOcc's user tools, each run as ``python -m occplug_queryocc.tools.<name>``: ``ablate`` (the supervision
ablation), ``bench`` and ``diagnose`` (where a trained model predicts occupied space that is free). Nothing here is
imported by ``plugin.py``."""
