"""Test helpers for occplug and plugin authors (opt-in: ``pytest_plugins = ["occplug.testing"]``).

Fixtures: ``tiny_batch`` (a collated batch of the tiny synthetic world), ``isolated_registry``
(a registry with the built-ins plus only the plugins you name). Functions: :func:`hand_batch` /
:func:`label_batch` (batches built by hand: cameras, or labels and masks for metric and supervision tests), :func:`check_component`
(the conformance check every registered component passes) and :func:`run_config` (a short fit of
a config, through the same code the CLI runs). :data:`TINY_FIT`: the overrides of a 2-step CPU fit.
"""

from __future__ import annotations

from .conformance import check_component, label_grid, tiny_context
from .fixtures import (
    hand_batch,
    isolated_registry,
    label_batch,
    make_tiny_batch,
    tiny_batch,
)
from .runs import TINY_FIT, run_config
from .tools import check_tool_help, check_tool_main_guard, check_tools_import_quietly

__all__ = [
    "TINY_FIT",
    "check_component",
    "check_tool_help",
    "check_tool_main_guard",
    "check_tools_import_quietly",
    "hand_batch",
    "isolated_registry",
    "label_batch",
    "label_grid",
    "make_tiny_batch",
    "run_config",
    "tiny_context",
    "tiny_batch",
]
