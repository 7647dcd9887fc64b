"""``occplug plugins``: where each component's code is, and quiet ends when the reader closes the pipe."""

from __future__ import annotations

import importlib
import json
import subprocess
import sys

from occplug.cli import main


def test_text_output_names_each_components_code(capsys):
    assert main(["plugins", "--kind", "encoder"]) == 0
    out = capsys.readouterr().out
    line = next(line for line in out.splitlines() if " small_cnn " in line)
    assert "occplug.components.encoders:SmallCNN" in line


def test_json_sources_resolve_to_the_registered_class(capsys):
    assert main(["plugins", "--json"]) == 0
    reports = json.loads(capsys.readouterr().out)
    from occplug.plugins import get_registry

    registry = get_registry()
    checked = 0
    for report in reports:
        assert report["sources"].keys() == report["components"].keys()
        for kind, names in report["components"].items():
            for name in names:
                module, _, qualname = report["sources"][kind][name].partition(":")
                target = importlib.import_module(module)
                for part in qualname.split("."):
                    target = getattr(target, part)
                assert target is registry.get(kind, name).factory
                checked += 1
    assert checked > 20


def test_a_closed_pipe_ends_quietly():
    # the reader goes away before the command writes (as `grep -q` after its match): closed before the
    # interpreter has even started, so the first write meets a broken pipe
    proc = subprocess.Popen(
        [sys.executable, "-m", "occplug.cli", "plugins", "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    proc.stdout.close()
    stderr = proc.stderr.read().decode()
    proc.wait(timeout=120)
    assert "Traceback" not in stderr and "BrokenPipeError" not in stderr, stderr
    assert proc.returncode in (0, 141)
