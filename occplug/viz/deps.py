"""The optional packages behind the pictures (the ``viz`` extra), imported on demand.

The core never needs them: ``occplug fit`` runs without matplotlib or rerun-sdk. Every module of
:mod:`occplug.viz` that draws a PNG calls :func:`require_matplotlib` first; the Rerun export calls
:func:`require_rerun`. A missing package is one clear error naming the extra to install.
"""

from __future__ import annotations

import importlib
from types import ModuleType

__all__ = ["MissingExtraError", "require_matplotlib", "require_rerun"]

INSTALL_HINT = "pip install 'occplug[viz]'"


class MissingExtraError(ImportError, ValueError):
    """An optional package of the ``viz`` extra is not installed.

    It is an ``ImportError`` (what it is) and a ``ValueError`` (so code that turns bad component
    arguments into one-line user errors, e.g. building a ``callbacks:`` entry, reports it as such).
    """


def _require(module: str, package: str, purpose: str) -> ModuleType:
    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingExtraError(f"{purpose} needs {package}, which is not installed: {INSTALL_HINT}") from None


def require_matplotlib(purpose: str = "drawing PNG panels") -> ModuleType:
    """``matplotlib`` with the non-interactive Agg backend; :class:`MissingExtraError` if absent.

    Figures are built as ``matplotlib.figure.Figure`` objects (never through ``pyplot``), so no
    GUI backend or global figure state is involved.
    """
    mpl = _require("matplotlib", "matplotlib", purpose)
    importlib.import_module("matplotlib.figure")
    importlib.import_module("matplotlib.backends.backend_agg")
    return mpl


def require_rerun(purpose: str = "writing a Rerun recording") -> ModuleType:
    """The ``rerun`` module of rerun-sdk; :class:`MissingExtraError` if absent."""
    return _require("rerun", "rerun-sdk", purpose)
