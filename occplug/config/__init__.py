"""Config composition, validation and reference resolution."""

from occplug.settings import make_settings, settings
from occplug.slots import TOP_LEVEL, Slot

from .compose import Composed, compose, read_config, resolve
from .errors import ConfigError
from .phases import phase_specs
from .refs import resolve_ref, search_path
from .validate import validate

__all__ = [
    "TOP_LEVEL",
    "Composed",
    "ConfigError",
    "Slot",
    "compose",
    "make_settings",
    "phase_specs",
    "read_config",
    "resolve",
    "resolve_ref",
    "search_path",
    "settings",
    "validate",
]
