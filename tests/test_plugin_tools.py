"""The method plugins' tools (``python -m occplug_<m>.tools.<name>``: ablations, benchmarks, diagnostics): each prints
its help, and importing one only defines things (its work runs in ``main()``), checked with occplug.testing's
tool checks, which any plugin's own tests can use the same way."""

from __future__ import annotations

import pytest

from occplug.testing import check_tool_help, check_tool_main_guard, check_tools_import_quietly

TOOLS = [
    "occplug_queryocc.tools.ablate",
    "occplug_queryocc.tools.bench",
    "occplug_queryocc.tools.diagnose",
    "occplug_occle.tools.ablate",
    "occplug_occle.tools.bench",
    "occplug_occle.tools.memory",
    "occplug_occle.tools.options",
    "occplug_duocc.tools.ablate",
    "occplug_duocc.tools.bench",
    "occplug_duocc.tools.fit_anchors",
    "occplug_duocc.tools.fit_class_weights",
    "occplug_duocc.tools.selection",
    "occplug_duocc.tools.stream_gain",
]


@pytest.mark.parametrize("module", TOOLS)
def test_the_tool_runs_as_a_module_and_prints_its_help(module, tmp_path):
    check_tool_help(module, tmp_path)


def test_importing_the_tools_only_defines_things(tmp_path):
    check_tools_import_quietly(TOOLS, tmp_path)


@pytest.mark.parametrize("module", TOOLS)
def test_the_tool_does_its_work_under_the_main_guard(module):
    check_tool_main_guard(module)
