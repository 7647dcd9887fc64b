"""The one exception type for user mistakes that components, data modules and the core detect.

A component that finds the user's data or settings do not fit it (an image size its stride does
not divide, a label file of the wrong shape) raises :class:`UserError` with one line naming the
key, file or value and what was expected. The CLI prints it as ``error: <message>`` with exit code
2, and ``occplug fit`` runs one batch through the model before it writes anything, so such a
mistake costs seconds and leaves no run directory behind.
"""

from __future__ import annotations

__all__ = ["ConfigError", "UserError"]


class UserError(ValueError):
    """A user mistake; ``str(err)`` is the one-line message. A ``ValueError``, so older ``except
    ValueError`` handlers keep working."""


class ConfigError(UserError):
    """A user mistake in a config file or override. ``str(err)`` is the one-line message
    (also importable as ``occplug.config.ConfigError``)."""
