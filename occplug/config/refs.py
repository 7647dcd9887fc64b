"""Resolving config references to files.

A reference is, in order of lookup:

1. a path to an existing file (``configs/baseline.yaml``; ``.yaml`` may be omitted), relative
   to the including file's folder for ``base:`` entries, else to the working directory;
2. ``<plugin>/<path>``: a file in the config folder a plugin returns from ``occplug_config_dir``
   (``occplug/...`` is the core's own ``occplug/configs``), e.g. ``queryocc/base``;
3. ``<path>`` under ``./configs/`` (the project's recipes), e.g. ``baseline``.
"""

from __future__ import annotations

from pathlib import Path

from occplug.plugins import config_dirs

from .errors import ConfigError

__all__ = ["resolve_ref", "search_path"]


def _with_yaml(path: Path) -> list[Path]:
    return [path] if path.suffix in (".yaml", ".yml") else [path, path.with_name(path.name + ".yaml")]


def search_path() -> list[tuple[str, Path]]:
    """``(prefix, folder)`` pairs searched for named configs, in order."""
    pairs = [(name, folder) for name, folder in sorted(config_dirs().items())]
    pairs.append(("", Path.cwd() / "configs"))
    return pairs


def resolve_ref(ref: str, relative_to: Path | None = None) -> Path:
    """The file a config reference names.

    Raises:
        ConfigError: nothing matches; the message lists where it looked.
    """
    ref = str(ref).strip()
    if not ref:
        raise ConfigError("empty config reference")
    raw = Path(ref).expanduser()
    anchors = [relative_to] if relative_to is not None and not raw.is_absolute() else []
    anchors.append(Path.cwd())
    for anchor in anchors:
        for candidate in _with_yaml(raw if raw.is_absolute() else anchor / raw):
            if candidate.is_file():
                return candidate.resolve()
    head, _, rest = ref.partition("/")
    dirs = config_dirs()
    if rest and head in dirs:
        for candidate in _with_yaml(dirs[head] / rest):
            if candidate.is_file():
                return candidate
        raise ConfigError(f"config '{ref}': plugin '{head}' ships no '{rest}' (looked in {dirs[head]})")
    for candidate in _with_yaml(Path.cwd() / "configs" / raw):
        if candidate.is_file():
            return candidate.resolve()
    where = ", ".join(f"{name}/" for name in sorted(dirs)) or "(no plugin config folders)"
    raise ConfigError(f"config '{ref}' not found: not a file, and not a known config under {where} or ./configs/")
