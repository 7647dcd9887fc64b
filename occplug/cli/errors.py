"""CLI errors reported as one line with exit code 2."""

from __future__ import annotations


class UsageError(Exception):
    """A user mistake on the command line (bad path, missing checkpoint, ...)."""
