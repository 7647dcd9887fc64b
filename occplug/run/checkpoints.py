"""The run's user-facing error and the one safe way a checkpoint file is read (both re-exported by :mod:`.runner`).

They sit below :mod:`.runner` so that :mod:`.weights`, which :func:`.runner.fit` calls, can use them without an
import circle.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

__all__ = ["RunError", "load_checkpoint"]


class RunError(Exception):
    """A user-facing problem with a run (exit code 2 from the CLI)."""


def load_checkpoint(path: Path) -> dict[str, Any]:
    """Read a checkpoint with ``weights_only=True``; clear errors for a missing or foreign file."""
    path = Path(path)
    if not path.is_file():
        raise RunError(f"checkpoint {path} does not exist")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise RunError(
            f"checkpoint {path} cannot be read safely (weights_only=True): {str(exc).splitlines()[0]}"
        ) from None
