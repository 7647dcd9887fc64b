"""OccLE's user tools, each run as ``python -m occplug_occle.tools.<name>``: ``ablate`` (the paper's tables),
``bench`` (the building blocks' speed) and ``memory`` (a training step's peak memory by grid size). Nothing here is
imported by ``plugin.py``."""
