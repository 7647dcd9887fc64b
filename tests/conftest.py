"""Shared test setup: a private cache for the synthetic world and the occplug test helpers."""

import os
import tempfile

pytest_plugins = ["occplug.testing"]

# Keep generated frames out of the user's cache; shared by every test of one session.
os.environ.setdefault("OCCPLUG_CACHE", os.path.join(tempfile.gettempdir(), "occplug-test-cache"))
