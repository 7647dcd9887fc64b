"""Constraints on component arguments: ``Annotated[int, Positive]`` (see :mod:`occplug.constraints`).

They live in the leaf module :mod:`occplug.constraints` so that data modules and metrics, which the
config package's validator imports, can declare them without an import circle; this is their
documented home for plugin authors.
"""

from __future__ import annotations

from occplug.constraints import (
    Constraint,
    Fraction,
    Length,
    NonNegative,
    Positive,
    Range,
    UnitInterval,
    constraints_of,
    violated,
)

__all__ = [
    "Constraint",
    "Fraction",
    "Length",
    "NonNegative",
    "Positive",
    "Range",
    "UnitInterval",
    "constraints_of",
    "violated",
]
