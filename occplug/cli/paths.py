"""Checks of the path arguments of every command, run before anything is read or written.

Each returns the path or raises :class:`~occplug.cli.errors.UsageError` with one line naming the
option, the path and what was expected: a file where a folder is expected (or the reverse), a path
below a file, a missing parent folder, an unwritable folder. Inputs must exist; outputs may exist
(as the right kind) or be created in an existing, writable folder -- the commands never create
missing parents, so a typo does not leave a stray tree.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from occplug.config.errors import ConfigError
from occplug.config.refs import resolve_ref

from .errors import UsageError

__all__ = ["config_refs", "input_dir", "input_file", "input_path", "output_dir", "output_file"]


def _blocking_file(path: Path) -> Path | None:
    """The nearest ancestor of ``path`` that exists and is not a folder (a path below a file), if any."""
    for parent in path.parents:
        if parent.exists():
            return None if parent.is_dir() else parent
    return None


def _missing(flag: str, path: Path, what: str) -> UsageError:
    blocker = _blocking_file(path)
    if blocker is not None:
        return UsageError(f"{flag} {path}: {blocker} is a file, not a folder")
    return UsageError(f"{flag} {path}: {what} (it does not exist)")


def input_file(flag: str, value: str | Path) -> Path:
    """An existing file (``--ckpt``, ``--origins``, ``--splits FILE``)."""
    path = Path(value)
    if path.is_dir():
        raise UsageError(f"{flag} {path}: is a folder; expected a file")
    if not path.is_file():
        raise _missing(flag, path, "no such file")
    return path


def input_dir(flag: str, value: str | Path, missing: str = "not a folder") -> Path:
    """An existing folder (data roots, ``--pred``, ``--gt``, ``--resume``); ``missing`` says what an
    absent one is."""
    path = Path(value)
    if path.exists() and not path.is_dir():
        raise UsageError(f"{flag} {path}: is a file; expected a folder")
    if not path.is_dir():
        raise _missing(flag, path, missing)
    return path


def input_path(flag: str, value: str | Path, what: str = "file or folder") -> Path:
    """An existing file or folder (``--index``: the index folder or its ``.npz``), described as ``what``."""
    path = Path(value)
    if not path.exists():
        raise _missing(flag, path, f"no {what} there")
    return path


def _writable_parent(flag: str, path: Path) -> None:
    parent = path.absolute().parent
    if not parent.exists():
        blocker = _blocking_file(path.absolute())
        if blocker is not None:
            raise UsageError(f"{flag} {path}: {blocker} is a file, not a folder")
        raise UsageError(f"{flag} {path}: its folder {parent} does not exist")
    if not parent.is_dir():
        raise UsageError(f"{flag} {path}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise UsageError(f"{flag} {path}: cannot write in {parent} (permission denied)")


def output_dir(flag: str, value: str | Path, empty: bool = False, make_parents: bool = False) -> Path:
    """A folder to write into: an existing folder (``empty``: without entries) or a new one in an
    existing, writable folder; with ``make_parents`` (run directories, like the default ``runs/<time>``)
    missing parent folders are created too, below the nearest existing, writable folder."""
    path = Path(value)
    if path.exists():
        if not path.is_dir():
            raise UsageError(f"{flag} {path}: is a file; expected a folder")
        if not os.access(path, os.W_OK | os.X_OK):
            raise UsageError(f"{flag} {path}: cannot write in it (permission denied)")
        if empty and any(path.iterdir()):
            raise UsageError(f"{flag} {path}: the folder exists and is not empty")
        return path
    if make_parents:
        blocker = _blocking_file(path.absolute())
        if blocker is not None:
            raise UsageError(f"{flag} {path}: {blocker} is a file, not a folder")
        existing = next(p for p in path.absolute().parents if p.exists())
        if not os.access(existing, os.W_OK | os.X_OK):
            raise UsageError(f"{flag} {path}: cannot write in {existing} (permission denied)")
        return path
    _writable_parent(flag, path)
    return path


def output_file(flag: str, value: str | Path) -> Path:
    """A file to write: absent or an existing file (replaced), in an existing, writable folder."""
    path = Path(value)
    if path.is_dir():
        raise UsageError(f"{flag} {path}: is a folder; expected a file")
    _writable_parent(flag, path)
    return path


def config_refs(refs: Sequence[str]) -> None:
    """Every ``-c`` reference names a config file (a path, or a plugin's or ./configs/ reference).

    Raises:
        UsageError: a folder, or a path below a file.
        ConfigError: nothing matches (the message lists where it looked).
    """
    for ref in refs:
        try:
            resolve_ref(ref)
        except ConfigError:  # a reference may match a folder's name (occplug/data/synthetic): judge only misses
            path = Path(ref).expanduser()
            if path.is_dir():
                raise UsageError(f"-c {ref}: is a folder; expected a config file") from None
            blocker = _blocking_file(path)
            if blocker is not None:
                raise UsageError(f"-c {ref}: {blocker} is a file, not a folder") from None
            raise
