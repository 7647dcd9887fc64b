"""The one exception type for user mistakes that components, data modules and the core detect.

A component that finds the user's data or settings do not fit it (an image size its stride does
not divide, a label file of the wrong shape) raises :class:`UserError` with one line naming the
key, file or value and what was expected. The CLI prints it as ``error: <message>`` with exit code
2, and ``occplug fit`` runs one batch through the model before it writes anything, so such a
mistake costs seconds and leaves no run directory behind.
"""

from __future__ import annotations

import difflib

__all__ = ["ComponentArgumentError", "ConfigError", "UserError", "closest"]


class UserError(ValueError):
    """A user mistake; ``str(err)`` is the one-line message. A ``ValueError``, so older ``except
    ValueError`` handlers keep working."""


class ConfigError(UserError):
    """A user mistake in a config file or override. ``str(err)`` is the one-line message
    (also importable as ``occplug.config.ConfigError``)."""


def closest(name: str, choices: list[str]) -> str | None:
    """The closest of ``choices`` to ``name`` (difflib), or None if nothing is close: the "did you mean" of an
    error message."""
    match = difflib.get_close_matches(name, choices, n=1, cutoff=0.6)
    return match[0] if match else None


class ComponentArgumentError(ValueError):
    """A node's argument the factory does not take, or a given argument the parent does not pass.

    Attributes:
        key: the argument's name (a caller that knows the node's config path prefixes it).
    """

    def __init__(self, message: str, key: str) -> None:
        super().__init__(message)
        self.key = key
