"""Config errors: one line each, naming the file or key and what was expected."""

from __future__ import annotations

from occplug.errors import UserError

__all__ = ["ConfigError"]


class ConfigError(UserError):
    """A user mistake in a config file or override. ``str(err)`` is the one-line message."""
