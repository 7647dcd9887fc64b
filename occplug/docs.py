"""Tables the docs print, generated from the code (a test holds ``docs/plugins.md`` to them).

It reads the facade's :data:`occplug.PUBLIC_MODULES`, so it sits beside the facade, above every other module
(``occplug.kinds`` stays a leaf the registry imports).
"""

from __future__ import annotations

import importlib

import occplug
from occplug.kinds import KINDS

__all__ = ["markdown_table", "public_name"]


def public_name(cls: type) -> str:
    """The shortest public import path of ``cls``: the first module of :data:`occplug.PUBLIC_MODULES` (the facade
    first) that exports it, else its own module (Lightning's ``Callback``, from ``lightning.pytorch``)."""
    for name in occplug.PUBLIC_MODULES:
        module = importlib.import_module(name)
        if cls.__name__ in getattr(module, "__all__", ()) and getattr(module, cls.__name__, None) is cls:
            return f"{name}.{cls.__name__}"
    top = "lightning.pytorch" if cls.__module__.startswith("lightning.pytorch") else cls.__module__
    return f"{top}.{cls.__qualname__}"


def markdown_table() -> str:
    """The table of kinds in ``docs/plugins.md``, generated from :data:`KINDS` and the interfaces (a test
    holds the docs to it)."""
    lines = ["| kind | interface | place in a config | given | contract |", "|---|---|---|---|---|"]
    for kind in KINDS.values():
        given = ", ".join(f"`{g}`" for g in kind.given()) or "—"
        lines.append(
            f"| {kind.name} | `{public_name(kind.interface())}` | `{kind.place}` | {given} | {kind.contract} |"
        )
    return "\n".join(lines) + "\n"
