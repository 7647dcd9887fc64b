"""Constraints on component arguments, declared where their types are: ``Annotated[int, Positive]``.

Config validation checks them for built-in and plugin components alike and names the key, the
value and the rule in one line (``model.encoder.out_channels: expected an int > 0, got -1``). A
constraint on a list's element type (``list[Annotated[float, Positive]]``) applies to every
element; :class:`Length` bounds a list's length.

Each constraint can also list values that violate it (:meth:`Constraint.violations`), so a test
generated from the registry proves every declared rule is enforced.

Beyond the declared rules, config validation holds every number in range by default: a float finite, an int
within 64 bits (:func:`occplug.config.validate.out_of_range`).

A leaf module (it imports nothing of occplug), so data modules and metrics declare rules without an
import circle through the config package. It is the constraints' one home: plugins import them from here.
"""

from __future__ import annotations

import difflib
import math
import typing
from dataclasses import dataclass
from typing import Any

__all__ = [
    "Constraint",
    "Fraction",
    "LabelIds",
    "Length",
    "NonNegative",
    "Positive",
    "Range",
    "UnitInterval",
    "check_choices",
    "choices_of",
    "describe_choices",
    "constraints_of",
    "describe_rules",
    "violated",
]


class Constraint:
    """A rule a config value must satisfy (subclasses: :class:`Range`, :class:`Length`)."""

    def holds(self, value: Any) -> bool:
        """Whether ``value`` (already of the right type) satisfies the rule."""
        raise NotImplementedError

    def describe(self) -> str:
        """The rule in words, e.g. ``"> 0"``."""
        raise NotImplementedError

    def violations(self) -> list[Any]:
        """Values of the right type that break the rule (for generated tests)."""
        raise NotImplementedError


@dataclass(frozen=True)
class Range(Constraint):
    """``low <(=) value <(=) high``; NaN never satisfies a range.

    Attributes:
        low, high: bounds (None: unbounded on that side).
        low_open, high_open: whether a bound itself is excluded.
    """

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False

    def holds(self, value: Any) -> bool:
        if not isinstance(value, (int, float)) or isinstance(value, bool) or math.isnan(value):
            return False
        if self.low is not None and (value <= self.low if self.low_open else value < self.low):
            return False
        return not (self.high is not None and (value >= self.high if self.high_open else value > self.high))

    def describe(self) -> str:
        low = None if self.low is None else f"{'>' if self.low_open else '>='} {_num(self.low)}"
        high = None if self.high is None else f"{'<' if self.high_open else '<='} {_num(self.high)}"
        if low and high:
            return (
                f"in {'(' if self.low_open else '['}{_num(self.low)}, {_num(self.high)}{')' if self.high_open else ']'}"
            )
        return low or high or "any number"

    def violations(self) -> list[Any]:
        out: list[Any] = [math.nan]
        if self.low is not None:
            out += [self.low] if self.low_open else []
            out += [self.low - 1]
        if self.high is not None:
            out += [self.high] if self.high_open else []
            out += [self.high + 1]
        return out


@dataclass(frozen=True)
class Length(Constraint):
    """A list's length: exactly ``exact``, or within ``[min, max]``."""

    exact: int | None = None
    min: int | None = None
    max: int | None = None

    def holds(self, value: Any) -> bool:
        if not isinstance(value, (list, tuple)):
            return True
        n = len(value)
        if self.exact is not None:
            return n == self.exact
        return (self.min is None or n >= self.min) and (self.max is None or n <= self.max)

    def describe(self) -> str:
        if self.exact is not None:
            return f"a list of {self.exact}"
        if self.max is None:
            return f"a list of at least {self.min}"
        return f"a list of {self.min or 0} to {self.max}"

    def violations(self) -> list[Any]:
        if self.exact is not None:
            return [[0] * (self.exact + 1)] + ([[0] * (self.exact - 1)] if self.exact > 0 else [])
        out = [[0] * (self.min - 1)] if self.min else []
        return out + ([[0] * (self.max + 1)] if self.max is not None else [])


#: ``> 0`` (channel counts, sizes, learning rates).
Positive = Range(low=0, low_open=True)
#: ``>= 0`` (loss weights, counts that may be zero, warm-up steps).
NonNegative = Range(low=0)
#: ``[0, 1]`` (probabilities, thresholds, ratios).
UnitInterval = Range(low=0, high=1)
#: ``(0, 1]`` (fractions of a set).
Fraction = Range(low=0, high=1, low_open=True)


def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else str(x)


@dataclass(frozen=True)
class LabelIds(Constraint):
    """A list of label ids of the run's classes: every id ``< count``.

    Declared as ``LabelIds()`` beside the elements' own rule (``tuple[Annotated[int, NonNegative], ...]``): the
    class count is the data module's, unknown where the rule is declared. Config validation reads the data
    module's classes (its ``class_names`` class attribute) and checks the rule with ``count`` filled in, so a class
    id the data set does not have is one line before anything is built. With ``count`` None it admits every list.
    """

    count: int | None = None

    def holds(self, value: Any) -> bool:
        return self.count is None or all(not isinstance(v, int) or v < self.count for v in value)

    def describe(self) -> str:
        count = "the data set's" if self.count is None else f"the data set's {self.count}"
        return f"label ids of {count} classes" + ("" if self.count is None else f" (0 to {self.count - 1})")

    def violations(self) -> list[Any]:
        return [] if self.count is None else [[self.count]]


def constraints_of(annotation: Any) -> list[Constraint]:
    """The constraints declared on ``annotation`` itself (``Annotated[..., C]``, also inside ``X | None``)."""
    if typing.get_origin(annotation) is typing.Annotated:
        return [m for m in annotation.__metadata__ if isinstance(m, Constraint)]
    found: list[Constraint] = []
    if typing.get_origin(annotation) in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        for arg in typing.get_args(annotation):
            found += constraints_of(arg)
    return found


def _element_annotation(annotation: Any) -> Any | None:
    """The element annotation of a list-like annotation (through Annotated and Optional), if any."""
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _element_annotation(typing.get_args(annotation)[0])
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        for arg in typing.get_args(annotation):
            found = _element_annotation(arg)
            if found is not None:
                return found
        return None
    import collections.abc as cabc

    if origin in (list, tuple, cabc.Sequence):
        args = typing.get_args(annotation)
        return args[0] if args else None
    return None


def violated(value: Any, annotation: Any) -> str | None:
    """The first rule ``value`` breaks, described for an error message (``"an int > 0"``), or None.

    ``value`` must already fit the annotation's type. ``None`` satisfies every rule (an optional
    argument switched off).
    """
    if value is None:
        return None
    for rule in constraints_of(annotation):
        if not rule.holds(value):
            return _with_type(rule, value)
    element = _element_annotation(annotation)
    if element is not None and isinstance(value, (list, tuple)):
        for item in value:
            problem = violated(item, element)
            if problem is not None:
                return f"every element {problem}"
    return None


def describe_rules(annotation: Any) -> str:
    """The rules declared on ``annotation`` in words (``"> 0"``, ``"every element in [0, 1]"``), or ``""``."""
    parts = [rule.describe() for rule in constraints_of(annotation)]
    element = _element_annotation(annotation)
    if element is not None and (inner := describe_rules(element)):
        parts.append(f"every element {inner}")
    return ", ".join(parts)


def _with_type(rule: Constraint, value: Any) -> str:
    if isinstance(rule, (Length, LabelIds)):
        return rule.describe()
    kind = "an int" if isinstance(value, int) and not isinstance(value, bool) else "a number"
    return f"{kind} {rule.describe()}"


def choices_of(annotation: Any) -> tuple[Any, ...]:
    """The values of the ``Literal`` in ``annotation`` (inside ``Annotated`` / a union), or ``()``."""
    origin = typing.get_origin(annotation)
    if origin is typing.Literal:
        return typing.get_args(annotation)
    if origin is typing.Annotated:
        return choices_of(typing.get_args(annotation)[0])
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        return tuple(c for arg in typing.get_args(annotation) for c in choices_of(arg))
    return ()


def describe_choices(choices: tuple[Any, ...]) -> str:
    """``"'add' or 'concat'"``: the ``repr`` of each choice, the last joined by "or"."""
    words = [repr(c) for c in choices]
    return words[0] if len(words) == 1 else f"{', '.join(words[:-1])} or {words[-1]}"


def check_choices(func: Any, who: str, **values: Any) -> None:
    """Check each ``name=value`` against the ``Literal`` annotating ``func``'s parameter ``name``.

    The annotation is the one list of choices (config validation reads the same one), so a constructor
    checks a directly passed value without a second list::

        def __init__(self, fusion: Literal["add", "concat"] = "add"):
            check_choices(StreamAggregation.__init__, "StreamAggregation", fusion=fusion)

    Raises:
        ValueError: ``"{who} {name} must be 'add' or 'concat', got 'ad'; did you mean 'add'?"`` (one line).
        TypeError: a named parameter that is not ``Literal``-annotated (a programming error).
    """
    hints = typing.get_type_hints(func, include_extras=True)
    for name, value in values.items():
        allowed = choices_of(hints.get(name))
        if not allowed:
            raise TypeError(f"check_choices: {who} parameter {name!r} is not annotated with a Literal")
        if not any(type(value) is type(c) and value == c for c in allowed):
            near = difflib.get_close_matches(str(value), [c for c in allowed if isinstance(c, str)], n=1)
            hint = f"; did you mean {near[0]!r}?" if near and isinstance(value, str) else ""
            raise ValueError(f"{who} {name} must be {describe_choices(allowed)}, got {value!r}{hint}")
