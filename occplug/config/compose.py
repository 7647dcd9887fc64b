"""Composing a config from files and command-line overrides.

Rules:

1. A file may start with ``base: [ref, ...]`` (see :mod:`occplug.config.refs`). Bases load
   depth-first and merge in order, then the file's own body.
2. Mappings deep-merge; lists and scalars replace.
3. When a component node's ``type`` changes, its old arguments that the new component does not
   accept are dropped (no stale kwargs); those it accepts (e.g. ``grid``) carry over.
4. Several ``-c`` files merge in order; ``key=value`` overrides (values parsed as YAML 1.2, so
   ``optimizer.lr=1e-3`` is a float) apply last; ``~key`` deletes a key.
5. ``${...}`` interpolations resolve after everything is merged.

Files and override values are read as YAML 1.2, with limits (:mod:`occplug.config.yamlio`).
Every leaf remembers the file or override that last set it (``occplug config show --explain``).
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from occplug.plugins import get_registry
from occplug.slots import component_params, slot_at

from .errors import ConfigError
from .refs import resolve_ref
from .yamlio import check_interpolations, parse_yaml, read_yaml

__all__ = ["Composed", "compose", "read_config", "resolve"]


@dataclass
class Composed:
    """A merged (unresolved) config and where each leaf came from."""

    data: dict[str, Any]
    sources: dict[str, str] = field(default_factory=dict)
    files: list[Path] = field(default_factory=list)

    def resolved(self) -> dict[str, Any]:
        """The config with interpolations resolved (plain containers)."""
        return resolve(self.data, self.sources)


def resolve(data: dict[str, Any], sources: dict[str, str] | None = None) -> dict[str, Any]:
    """Resolve ``${...}`` interpolations, within bounds (:func:`~occplug.config.yamlio.check_interpolations`).

    Raises:
        ConfigError: a broken interpolation, or one past the bounds; one line naming the key (and, given
            ``sources``, the file or override that set it).
    """
    check_interpolations(data, sources)
    try:
        return OmegaConf.to_container(OmegaConf.create(data), resolve=True)  # type: ignore[return-value]
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", None)
        where = (sources or {}).get(key or "")
        suffix = f" (set by {where})" if where else ""
        raise ConfigError(f"{key + ': ' if key else ''}{str(exc).splitlines()[0]}{suffix}") from None
    except (MemoryError, RecursionError):
        raise ConfigError("resolving the config's ${...} interpolations ran out of memory or depth") from None


def read_config(path: str | Path) -> dict[str, Any]:
    """One config file (or a run's ``config.yaml``) as a mapping, read as YAML 1.2 within limits.

    Raises:
        ConfigError: one line naming the file (unreadable, not UTF-8, invalid YAML, a non-plain tag, an alias
            bomb, not a mapping).
    """
    path = Path(path)
    data = read_yaml(path)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a config file must be a mapping at the top level, got {type(data).__name__}")
    return data


class _Merger:
    def __init__(self) -> None:
        self.data: dict[str, Any] = {}
        self.sources: dict[str, str] = {}
        self.files: list[Path] = []
        self.registry = get_registry()

    def load_file(self, path: Path, stack: tuple[Path, ...] = ()) -> None:
        if path in stack:
            chain = " -> ".join(str(p) for p in (*stack, path))
            raise ConfigError(f"{path}: circular base: {chain}")
        body = read_config(path)
        bases = body.pop("base", None) or []
        if isinstance(bases, str):
            bases = [bases]
        if not isinstance(bases, list) or not all(isinstance(b, str) for b in bases):
            raise ConfigError(f"{path}: 'base' must be a list of config references")
        for ref in bases:
            try:
                base_path = resolve_ref(ref, relative_to=path.parent)
            except ConfigError as exc:
                raise ConfigError(f"{path}: base {exc}") from None
            self.load_file(base_path, (*stack, path))
        self.files.append(path)
        self.merge(body, str(path))

    def merge(self, over: dict[str, Any], origin: str) -> None:
        self.data = self._merge(self.data, over, (), origin)

    def _merge(self, base: Any, over: Any, path: tuple[str, ...], origin: str) -> Any:
        if not (isinstance(base, dict) and isinstance(over, dict)):
            self._record(over, path, origin)
            return copy.deepcopy(over)
        out = dict(base)
        new_type, old_type = over.get("type"), base.get("type")
        if "type" in over and "type" in base and new_type != old_type:
            out = self._retype(base, new_type, path)
        for key, value in over.items():
            out[key] = self._merge(out.get(key), value, (*path, str(key)), origin)
        return out

    def _retype(self, node: dict[str, Any], new_type: Any, path: tuple[str, ...]) -> dict[str, Any]:
        """Keep only the arguments the new component accepts (rule 3)."""
        for key in [k for k in self.sources if _under(k, path)]:
            del self.sources[key]
        slot = slot_at(self.data, path, self.registry) if path else None
        if slot is None or not isinstance(new_type, str):
            return {}
        try:
            params = component_params(self.registry.get(slot.kind, new_type).factory)
        except LookupError:
            return {}
        return {k: v for k, v in node.items() if k in params}

    def _record(self, value: Any, path: tuple[str, ...], origin: str) -> None:
        dotted = ".".join(path)
        for key in [k for k in self.sources if _under(k, path)]:
            del self.sources[key]
        if isinstance(value, dict) and value:
            for k, v in value.items():
                self._record(v, (*path, str(k)), origin)
        else:
            self.sources[dotted] = origin

    def apply_override(self, item: str) -> None:
        if item.startswith("~"):
            self._delete(item[1:], item)
            return
        key, sep, raw = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(f"override '{item}': expected key=value (or ~key to delete)")
        if key.startswith("+"):
            raise ConfigError(f"override '{item}': no '+' prefix needed, write {key[1:]}={raw}")
        try:
            value = parse_yaml(raw, f"override '{item}'") if raw.strip() else None
        except ConfigError:  # not YAML (an unbalanced bracket, a stray colon): the text itself
            value = raw
        parts = key.split(".")
        phases = self.data.get("phases")
        declared = [str(name) for name in phases] if isinstance(phases, dict) else []
        if len(parts) > 1 and parts[0] == "phases" and parts[1] not in declared:
            # a misspelt phase would otherwise become a new phase that trains the whole model once more
            known = ", ".join(declared) or "none"
            raise ConfigError(
                f"override '{item}': the config has no phase '{parts[1]}' (its phases: {known}); "
                "declare a new phase in a config file"
            )
        nested: Any = value
        for part in reversed(parts):
            nested = {part: nested}
        self.merge(nested, f"override {item}")

    def _delete(self, key: str, item: str) -> None:
        parts = key.split(".")
        node: Any = self.data
        for part in parts[:-1]:
            if not isinstance(node, dict) or part not in node:
                raise ConfigError(f"override '{item}': there is no key '{key}' to delete")
            node = node[part]
        if not isinstance(node, dict) or parts[-1] not in node:
            raise ConfigError(f"override '{item}': there is no key '{key}' to delete")
        del node[parts[-1]]
        for k in [k for k in self.sources if _under(k, tuple(parts))]:
            del self.sources[k]


def _under(dotted: str, path: tuple[str, ...]) -> bool:
    prefix = ".".join(path)
    return not prefix or dotted == prefix or dotted.startswith(prefix + ".")


def compose(refs: Sequence[str], overrides: Sequence[str] = (), *, data: dict[str, Any] | None = None) -> Composed:
    """Compose config files (in order) and ``key=value`` overrides.

    Args:
        refs: config references (paths or ``plugin/name``), merged in order.
        overrides: dotlist items applied last.
        data: an already composed config to start from (e.g. one saved in a run directory).

    Raises:
        ConfigError: a missing file, bad YAML, a circular base or a malformed override.
    """
    merger = _Merger()
    if data is not None:
        merger.merge(copy.deepcopy(data), "saved config")
    for ref in refs:
        merger.load_file(resolve_ref(ref))
    for item in overrides:
        merger.apply_override(item)
    return Composed(merger.data, merger.sources, merger.files)
