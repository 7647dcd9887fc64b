"""Config composition, validation and reference resolution."""

from .compose import Composed, compose, resolve
from .errors import ConfigError
from .refs import resolve_ref, search_path
from .slots import TOP_LEVEL, Slot
from .validate import validate

__all__ = [
    "TOP_LEVEL",
    "Composed",
    "ConfigError",
    "Slot",
    "compose",
    "resolve",
    "resolve_ref",
    "search_path",
    "validate",
]
