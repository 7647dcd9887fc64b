"""Shared test setup: a private cache for the synthetic world, the occplug test helpers, and one CPU share per
pytest-xdist worker."""

import os
import tempfile

import torch

pytest_plugins = ["occplug.testing"]

# Keep generated frames out of the user's cache; shared by every test of one session (the cache writes each frame
# atomically, so parallel workers may generate the same world side by side).
os.environ.setdefault("OCCPLUG_CACHE", os.path.join(tempfile.gettempdir(), "occplug-test-cache"))

# Under pytest-xdist (pyproject's addopts) each worker gets its share of the cores: torch's default of one thread per
# core in every worker oversubscribes the machine. The variable also reaches the processes the tests start.
if "PYTEST_XDIST_WORKER_COUNT" in os.environ:
    _threads = max(1, (os.cpu_count() or 1) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"]))
    os.environ["OMP_NUM_THREADS"] = str(_threads)
    torch.set_num_threads(_threads)
