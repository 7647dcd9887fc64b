"""Nested settings: a component argument that is itself a group of settings, declared as a typed class.

A component whose constructor takes a group of settings (DuOcc's ``query_agg``, and the ``detector`` group
inside it) declares the group once, as a class whose fields carry their types, defaults and rules::

    from occplug.config import settings
    from occplug.constraints import Positive

    @settings
    class DetectorSettings:
        channels: Annotated[int, Positive] = 64
        num_queries: Annotated[int, Positive] = 64

    @settings
    class QueryAggSettings:
        v2q: bool = True
        max_queries: Annotated[int, Positive] | None = None
        detector: DetectorSettings = DetectorSettings()   # a group inside a group

    class MyScene(SceneRepresentation):
        def __init__(self, in_channels: int, query_agg: QueryAggSettings | None = None) -> None: ...

A config writes the group as a mapping (``query_agg: {v2q: false, detector: {num_queries: 900}}``). Config
validation checks it like a component's own arguments -- unknown keys (with the closest one), types and
``Annotated`` constraints -- naming the full dotted key (``model.scene.query_agg.detector.num_querys``), and
the builder (:meth:`occplug.Registry.build`) turns the mapping into the class before calling the constructor,
so the component receives a validated, typed, immutable object and checks no keys itself. Values the model
already knows (feature widths, the grid, the classes) are not settings: the component takes them as
``given`` arguments and hands them to whatever it builds from the settings.

A leaf module (as :mod:`occplug.slots` and :mod:`occplug.constraints`): the registry converts settings when it
builds, and the config package validates them, so neither may import the other's package. Plugins import
``settings`` from :mod:`occplug.config`.
"""

from __future__ import annotations

import collections.abc as cabc
import dataclasses
import types
import typing
from collections.abc import Callable, Mapping
from typing import Any, TypeVar

from occplug.slots import component_params

__all__ = ["is_settings", "make_settings", "settings", "settings_arguments", "settings_type"]

T = TypeVar("T")

_MARK = "__occplug_settings__"
_UNION = (typing.Union, types.UnionType)


@typing.dataclass_transform(frozen_default=True, kw_only_default=True)
def settings(cls: type[T]) -> type[T]:
    """Declare ``cls`` a group of settings: a frozen, keyword-only dataclass the validator and builder know.

    Each field is a setting: its annotation is its type (``Annotated[int, Positive]`` adds a rule, another
    ``@settings`` class a nested group, ``Literal[...]`` a choice) and its default the value a config may leave
    out; a field without a default is required.
    """
    cls = dataclasses.dataclass(frozen=True, kw_only=True)(cls)
    setattr(cls, _MARK, True)
    return cls


def is_settings(obj: Any) -> bool:
    """Whether ``obj`` is a class declared with :func:`settings`."""
    return isinstance(obj, type) and dataclasses.is_dataclass(obj) and bool(getattr(obj, _MARK, False))


def settings_type(annotation: Any) -> type | None:
    """The :func:`settings` class an annotation names, looked for through ``Annotated`` and unions, or None."""
    if is_settings(annotation):
        return annotation
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return settings_type(typing.get_args(annotation)[0])
    if origin in _UNION:
        for arg in typing.get_args(annotation):
            found = settings_type(arg)
            if found is not None:
                return found
    return None


def _tuple_element(annotation: Any) -> tuple[bool, Any]:
    """``(True, element annotation)`` when the annotation's list-like alternative is a ``tuple[X, ...]``."""
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _tuple_element(typing.get_args(annotation)[0])
    if origin in _UNION:
        for arg in typing.get_args(annotation):
            found = _tuple_element(arg)
            if found[0]:
                return found
        return False, None
    if origin is tuple:
        args = typing.get_args(annotation)
        return True, (args[0] if len(args) == 2 and args[1] is Ellipsis else Any)
    return annotation is tuple, Any


def _coerce(value: Any, annotation: Any) -> Any:
    """A config value as the field's type: a mapping -> its settings class, a list -> a tuple where declared."""
    cls = settings_type(annotation)
    if cls is not None and isinstance(value, Mapping):
        return make_settings(cls, value)
    is_tuple, element = _tuple_element(annotation)
    if is_tuple and isinstance(value, (list, tuple)):
        return tuple(_coerce(v, element) for v in value)
    return value


def make_settings(cls: type[T], value: Mapping[str, Any] | T) -> T:
    """An instance of the settings class ``cls`` from a (validated) config mapping; an instance is returned as is.

    Nested groups become their classes and lists become tuples where the field declares a tuple. Keys are not
    checked here: config validation did that (:func:`occplug.config.validate`); a key that is no field is a
    ``TypeError`` from the dataclass.
    """
    if isinstance(value, cls):
        return value
    hints = typing.get_type_hints(cls, include_extras=True)
    return cls(**{key: _coerce(v, hints.get(key, Any)) for key, v in dict(value).items()})


def settings_arguments(factory: Callable[..., Any], arguments: Mapping[str, Any]) -> dict[str, Any]:
    """``arguments`` of a component's constructor with each mapping given to a settings parameter made into it."""
    params = component_params(factory)
    out = dict(arguments)
    for key, value in arguments.items():
        if key in params and isinstance(value, cabc.Mapping):
            cls = settings_type(params[key][1])
            if cls is not None:
                out[key] = make_settings(cls, value)
    return out
