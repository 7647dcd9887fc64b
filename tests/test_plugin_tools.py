"""The method plugins' tools (``python -m occplug_<m>.<name>``: ablations, benchmarks, diagnostics): each prints
its help, and importing one only defines things (its work runs in ``main()``), checked with occplug.testing's
tool checks, which any plugin's own tests can use the same way."""

from __future__ import annotations

import pytest

from occplug.testing import check_tool_help, check_tool_main_guard, check_tools_import_quietly

TOOLS = [
    "occplug_queryocc.ablate",
    "occplug_queryocc.bench",
    "occplug_queryocc.diagnose",
    "occplug_queryocc.window_coverage",
    "occplug_occle.ablate",
    "occplug_occle.bench",
    "occplug_duocc.ablate",
    "occplug_duocc.bench",
    "occplug_duocc.fit_anchors",
    "occplug_duocc.fit_class_weights",
    "occplug_duocc.detector_overfit",
    "occplug_duocc.history_norm",
    "occplug_duocc.stream_gain",
]


@pytest.mark.parametrize("module", TOOLS)
def test_the_tool_runs_as_a_module_and_prints_its_help(module, tmp_path):
    check_tool_help(module, tmp_path)


def test_importing_the_tools_only_defines_things(tmp_path):
    check_tools_import_quietly(TOOLS, tmp_path)


@pytest.mark.parametrize("module", TOOLS)
def test_the_tool_does_its_work_under_the_main_guard(module):
    check_tool_main_guard(module)
