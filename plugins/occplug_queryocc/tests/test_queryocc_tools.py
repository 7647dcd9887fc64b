"""QueryOcc's tools, ``python -m occplug_queryocc.<name>`` (ablate, bench, window_coverage): each prints its help,
and importing one only defines things (its work runs in ``main()``)."""

from __future__ import annotations

import pytest

from occplug.testing import check_tool_help, check_tool_main_guard, check_tools_import_quietly

MODULES = ["occplug_queryocc.ablate", "occplug_queryocc.bench", "occplug_queryocc.window_coverage"]


@pytest.mark.parametrize("module", MODULES)
def test_the_tool_runs_as_a_module_and_prints_its_help(module, tmp_path):
    check_tool_help(module, tmp_path)


def test_importing_the_tools_only_defines_things(tmp_path):
    check_tools_import_quietly(MODULES, tmp_path)


@pytest.mark.parametrize("module", MODULES)
def test_the_tool_does_its_work_under_the_main_guard(module):
    check_tool_main_guard(module)
