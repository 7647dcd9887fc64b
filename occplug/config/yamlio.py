"""Reading and writing config YAML: YAML 1.2 through ruamel.yaml, with limits.

YAML 1.2 is what a user writes today: ``1e-3`` and ``2e-4`` are floats (YAML 1.1, PyYAML's rules, reads them
as strings), ``yes``/``no``/``on``/``off`` are strings, only ``true``/``false`` are booleans. Files and
``key=value`` overrides are read by the same loader (:func:`parse_yaml`), and the run's ``config.yaml`` is
written by the same library (:func:`dump_yaml`), so a dump reads back as the config that was run.

Limits, so that a hostile or broken file ends in one line instead of a hang or ``MemoryError``:

* a file is at most :data:`MAX_FILE_BYTES`;
* aliases (``*name``) may share nodes, but the document they expand to is at most :data:`MAX_NODES` nodes and
  :data:`MAX_DEPTH` levels deep, and may not contain itself (an alias bomb is refused before anything walks it);
* only plain data: the YAML 1.2 core schema's mappings, lists, strings, numbers, booleans and null; any other
  tag (``!!python/object``) is refused, and so is a duplicate key;
* ``${...}`` interpolations (resolved by OmegaConf after merging) are bounded by :func:`check_interpolations`.

Every error is a :class:`~occplug.errors.ConfigError` of one line that names the file (and line) or key.
"""

from __future__ import annotations

import io
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ruamel.yaml import YAML
from ruamel.yaml.comments import CommentedMap, CommentedSeq
from ruamel.yaml.error import MarkedYAMLError, YAMLError
from ruamel.yaml.nodes import ScalarNode
from ruamel.yaml.resolver import VersionedResolver
from ruamel.yaml.scalarstring import SingleQuotedScalarString

from .errors import ConfigError

__all__ = [
    "MAX_DEPTH",
    "MAX_FILE_BYTES",
    "MAX_INTERPOLATION_DEPTH",
    "MAX_INTERPOLATION_SIZE",
    "MAX_INTERPOLATIONS",
    "MAX_NODES",
    "check_interpolations",
    "dump_yaml",
    "parse_yaml",
    "read_yaml",
    "styled",
]

#: Largest config file read, in bytes.
MAX_FILE_BYTES = 16 * 1024 * 1024
#: Most nodes (mappings, lists, scalars) a document may expand to, aliases counted at each use.
MAX_NODES = 1_000_000
#: Deepest nesting of mappings and lists.
MAX_DEPTH = 64
#: Longest chain of ``${...}`` references (``a: ${b}``, ``b: ${c}``, ... counts one per step).
MAX_INTERPOLATION_DEPTH = 32
#: Most ``${...}`` resolutions that resolving the whole config may take (each use of a reference is one,
#: and a reference to a value that itself interpolates costs that value's resolutions again).
MAX_INTERPOLATIONS = 100_000
#: Longest value (in characters) that interpolation may build; the config's interpolated values may hold ten
#: times that in all.
MAX_INTERPOLATION_SIZE = 1_000_000


def _yaml() -> YAML:
    y = YAML(typ="safe", pure=True)  # pure: the same parser and messages everywhere, no C extension needed
    y.allow_duplicate_keys = False
    return y


def _dumper() -> YAML:
    y = YAML(typ="rt", pure=True)  # round-trip mode: block mappings with flow lists of scalars, key order kept
    y.width = 120
    y.representer.add_representer(type(None), lambda r, _: r.represent_scalar("tag:yaml.org,2002:null", "null"))
    y.representer.add_representer(float, _represent_float)
    return y


def _represent_float(representer: Any, value: float) -> Any:
    """``1.0e-20``, not ``1e-20``: a mantissa with a dot, which YAML 1.1 readers also take for a float."""
    if value != value:
        text = ".nan"
    elif value in (float("inf"), float("-inf")):
        text = ".inf" if value > 0 else "-.inf"
    else:
        text = repr(value)
        if "e" in text and "." not in text:
            text = text.replace("e", ".0e", 1)
    return representer.represent_scalar("tag:yaml.org,2002:float", text)


def styled(value: Any) -> Any:
    """Plain containers as ruamel's commented ones: mappings in block style, a list of scalars in flow style
    (``range: [-40, -40, -1, 40, 40, 5.4]``), keys as they are, tuples as lists. Commented containers (already
    styled, perhaps with comments) stay as they are."""
    if isinstance(value, (CommentedMap, CommentedSeq)):
        return value
    if isinstance(value, str):
        return _quoted_for_yaml_1_1(value)
    if isinstance(value, Mapping):
        out = CommentedMap((styled(k), styled(v)) for k, v in value.items())
        out.fa.set_block_style()
        return out
    if isinstance(value, (list, tuple)):
        seq = CommentedSeq(styled(v) for v in value)
        if all(not isinstance(v, (Mapping, list, tuple)) for v in value):
            seq.fa.set_flow_style()
        else:
            seq.fa.set_block_style()
        return seq
    return value


def _first_line(text: str) -> str:
    return " ".join(str(text).split("\n")[0].split())


def _describe_error(exc: YAMLError) -> str:
    problem = getattr(exc, "problem", None) or _first_line(str(exc))
    match = re.match(r"could not determine a constructor for the tag '([^']*)'", str(problem))
    if match:
        tag = match.group(1).replace("tag:yaml.org,2002:", "!!")
        return (
            f"tag '{tag}' is not allowed (a config holds plain data: mappings, lists, strings, numbers, booleans, null)"
        )
    context = getattr(exc, "context", None)
    return f"invalid YAML: {_first_line(problem)}" + (f" ({_first_line(context)})" if context else "")


def parse_yaml(text: str, where: str) -> Any:
    """Parse YAML 1.2 text into plain containers, within the limits above.

    Args:
        text: the document.
        where: what it is, for messages (a path, ``override 'k=v'``, ...).

    Raises:
        ConfigError: one line starting with ``where``.
    """
    try:
        data = _yaml().load(text)
    except MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = f" line {mark.line + 1}:" if mark is not None else ""
        raise ConfigError(f"{where}:{line} {_describe_error(exc)}") from None
    except YAMLError as exc:
        raise ConfigError(f"{where}: {_describe_error(exc)}") from None
    except RecursionError:
        raise ConfigError(f"{where}: nested too deeply (at most {MAX_DEPTH} levels)") from None
    _check_expansion(data, where)
    return data


def _check_expansion(data: Any, where: str) -> None:
    """Refuse a document whose aliases expand past :data:`MAX_NODES` or :data:`MAX_DEPTH`, or into itself.

    Shared nodes (what aliases construct) are counted once per use but visited once, so this takes time in
    the number of distinct nodes, however many the aliases expand to.
    """
    sizes: dict[int, int] = {}
    open_: set[int] = set()

    def size(node: Any, depth: int) -> int:
        if not isinstance(node, (dict, list)):
            return 1
        key = id(node)
        if key in open_:
            raise ConfigError(f"{where}: an alias refers to a node that contains it (a recursive document)")
        if key in sizes:
            return sizes[key]
        if depth > MAX_DEPTH:
            raise ConfigError(f"{where}: nested too deeply (at most {MAX_DEPTH} levels)")
        open_.add(key)
        children = list(node.values()) if isinstance(node, dict) else node
        total = 1 + sum(size(child, depth + 1) for child in children)
        open_.discard(key)
        if total > MAX_NODES:
            raise ConfigError(
                f"{where}: the document expands to more than {MAX_NODES:,} nodes (an alias bomb? aliases are "
                "counted at every use)"
            )
        sizes[key] = total
        return total

    size(data, 0)


def read_yaml(path: str | Path) -> Any:
    """Read a YAML 1.2 file (UTF-8) within the limits above; an empty file is ``None``.

    Raises:
        ConfigError: one line naming the file: unreadable, too large, not UTF-8, invalid YAML, a tag that is
            not plain data, a duplicate key, an alias bomb.
    """
    path = Path(path)
    try:
        with path.open("rb") as f:
            raw = f.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    if len(raw) > MAX_FILE_BYTES:
        raise ConfigError(f"{path}: larger than {MAX_FILE_BYTES // (1024 * 1024)} MiB; not a config file")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise ConfigError(
            f"{path}: line {line}: not UTF-8 text (byte 0x{raw[exc.start]:02x} at offset {exc.start})"
        ) from None
    return parse_yaml(text, str(path))


_YAML_1_1 = VersionedResolver(version=(1, 1))


def _quoted_for_yaml_1_1(text: str) -> str:
    """``text``, quoted where a YAML 1.1 reader (PyYAML's ``safe_load``, scripts reading a run's ``config.yaml``)
    would take it for something else (``yes``, ``on``, ``1:30``); YAML 1.2's own cases the dumper quotes."""
    if _YAML_1_1.resolve(ScalarNode, text, (True, False)) != "tag:yaml.org,2002:str":
        return SingleQuotedScalarString(text)
    return text


def dump_yaml(data: Any) -> str:
    """``data`` (plain containers; tuples become lists) as YAML 1.2 text that :func:`parse_yaml` reads back
    equal, and a YAML 1.1 reader too (strings such as ``yes`` quoted)."""
    stream = io.StringIO()
    _dumper().dump(styled(data), stream)
    return stream.getvalue()


# ----------------------------------------------------------------------------- interpolation limits
_INNERMOST = re.compile(r"(?<!\\)\$\{([^${}]*)\}")


def _references(text: str) -> list[str]:
    """The node references (``a.b``, ``.x``, ``..y[0]``) inside a string's ``${...}``, innermost first;
    resolver calls (``${oc.env:X}``) are left out (their arguments' references are in)."""
    found: list[str] = []
    while True:
        matches = list(_INNERMOST.finditer(text))
        if not matches:
            return found
        found += [m.group(1).strip() for m in matches if ":" not in m.group(1)]
        found += ["" for m in matches if ":" in m.group(1)]  # a resolver call: one resolution, no node
        text = _INNERMOST.sub("", text)


def _target(ref: str, at: tuple[Any, ...]) -> tuple[Any, ...] | None:
    """The absolute path a reference names, made in the node at path ``at`` (the referring value's parent), or
    None."""
    if not ref:
        return None
    dots = len(ref) - len(ref.lstrip("."))  # ``.x``: a key of the same node, ``..x``: of its parent, ...
    if dots and len(at) < dots - 1:
        return None
    base: tuple[Any, ...] = at[: len(at) - dots + 1] if dots else ()
    rest = ref[dots:].replace("[", ".").replace("]", "")
    return base + tuple(p for p in rest.split(".") if p)


def _lookup(root: Any, path: tuple[Any, ...]) -> tuple[tuple[Any, ...], Any] | None:
    """``(the path with the container's own keys, the value)`` at ``path``, or None."""
    node, canonical = root, []
    for part in path:
        if isinstance(node, dict) and part in node:
            node = node[part]
        elif isinstance(node, list) and str(part).isdigit() and int(part) < len(node):
            part = int(part)
            node = node[part]
        else:
            return None
        canonical.append(part)
    return tuple(canonical), node


def check_interpolations(data: dict[str, Any], origin: Mapping[str, str] | None = None) -> None:
    """Bound the work of resolving ``data``'s ``${...}`` interpolations before OmegaConf does it.

    OmegaConf resolves every use of a reference anew, so ``b: ${a}${a}``, ``c: ${b}${b}``, ... doubles the work
    and the string at each step. This counts, for every value, the resolutions and characters its
    interpolations take (each referenced value counted with its own interpolations, memoised, so counting is
    linear) and the longest chain of references.

    Args:
        data: a merged config (plain containers).
        origin: dotted key -> file or override that set it, named in the message.

    Raises:
        ConfigError: a chain deeper than :data:`MAX_INTERPOLATION_DEPTH`, more than :data:`MAX_INTERPOLATIONS`
            resolutions, or a string longer than :data:`MAX_INTERPOLATION_SIZE`; one line naming the key.
    """
    memo: dict[tuple[Any, ...], tuple[int, int, int]] = {}  # path -> (resolutions, characters, chain depth)
    stack: list[tuple[Any, ...]] = []
    built = [0]  # characters of every interpolated value, each counted once

    def fail(path: tuple[Any, ...], what: str) -> None:
        key = ".".join(map(str, path))
        where = (origin or {}).get(key)
        raise ConfigError(f"{key}: {what}" + (f" (set by {where})" if where else ""))

    def cost(node: Any, path: tuple[Any, ...]) -> tuple[int, int, int]:
        if path in memo:
            return memo[path]
        if path in stack:  # a cycle: OmegaConf names it when it resolves
            return 0, 0, 0
        stack.append(path)
        if isinstance(node, (dict, list)):
            items = node.items() if isinstance(node, dict) else enumerate(node)
            parts = [cost(child, (*path, key)) for key, child in items]
            result = (sum(p[0] for p in parts), sum(p[1] for p in parts), max((p[2] for p in parts), default=0))
        elif isinstance(node, str) and "${" in node:
            resolutions, size, depth = 0, len(node), 0
            for ref in _references(node):
                resolutions += 1
                target = _target(ref, path[:-1])
                found = _lookup(data, target) if target is not None else None
                if found is not None:
                    r, s, d = cost(found[1], found[0])
                    resolutions, size, depth = resolutions + r, size + s, max(depth, d)
            depth += 1
            if depth > MAX_INTERPOLATION_DEPTH:
                fail(
                    path, f"interpolations nest {depth} deep (at most {MAX_INTERPOLATION_DEPTH} references in a chain)"
                )
            if resolutions > MAX_INTERPOLATIONS:
                fail(
                    path,
                    f"resolving its interpolations takes over {MAX_INTERPOLATIONS:,} steps (an interpolation bomb?)",
                )
            if size > MAX_INTERPOLATION_SIZE:
                fail(path, f"its interpolations expand to over {MAX_INTERPOLATION_SIZE:,} characters")
            built[0] += size
            if built[0] > 10 * MAX_INTERPOLATION_SIZE:
                fail(path, f"the config's interpolations expand to over {10 * MAX_INTERPOLATION_SIZE:,} characters")
            result = (resolutions, size, depth)
        else:
            result = (0, len(str(node)), 0)
        stack.pop()
        memo[path] = result
        return result

    total = 0
    for key, value in data.items():
        total += cost(value, (key,))[0]
        if total > MAX_INTERPOLATIONS:
            fail((key,), f"resolving the config's interpolations takes over {MAX_INTERPOLATIONS:,} steps")
