"""The extension path: the example plugin is unknown before `pip install`, listed and trainable after."""

import json
import os
import subprocess
import sys
from importlib import util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "plugins" / "example"
CONFIG = EXAMPLE / "src" / "occplug_example" / "configs" / "tiny.yaml"


def occplug(*args, env=None):
    return subprocess.run(
        [sys.executable, "-m", "occplug.cli", *args], capture_output=True, text=True, env=env, cwd=ROOT
    )


@pytest.mark.skipif(
    util.find_spec("occplug_example") is not None, reason="the example plugin is installed here already"
)
def test_example_plugin_before_and_after_install(tmp_path):
    before = occplug("config", "show", "-c", str(CONFIG))
    assert before.returncode == 2
    assert "model.heads.occupancy.type: no head named 'tiny_mlp'" in before.stderr
    assert "voxel_classifier" in before.stderr  # lists the available heads

    target = tmp_path / "site"
    install = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--no-deps",
            "--no-build-isolation",
            "--no-index",
            "-q",
            "--target",
            str(target),
            str(EXAMPLE),
        ],
        capture_output=True,
        text=True,
    )
    assert install.returncode == 0, install.stderr
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(target), os.environ.get("PYTHONPATH", "")])}

    listed = json.loads(occplug("plugins", "--json", env=env).stdout)
    example = next(p for p in listed if p["name"] == "example")
    assert example["distribution"] == "occplug-example" and example["version"] == "0.1.0"
    assert example["components"] == {"head": ["tiny_mlp"]}

    # the plugin's own test suite (registration via entry point, conformance, a fit of example/tiny), in that one
    # process (-n 0: this repository's addopts would start xdist workers, each importing torch again)
    basetemp = tmp_path / "plugin-tests"
    tests = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-p",
            "no:cacheprovider",
            "-n",
            "0",
            f"--basetemp={basetemp}",
            str(EXAMPLE / "tests"),
        ],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
    )
    assert tests.returncode == 0, tests.stdout[-3000:] + tests.stderr[-2000:]

    # a checkpoint made with the plugin names it (and its version) where the plugin is not installed: the one
    # test_shipped_config_trains fitted (example/tiny with the plugin installed, as `occplug fit` runs it)
    run = basetemp / "test_shipped_config_trains0" / "run"
    assert (run / "checkpoints" / "last.ckpt").is_file(), sorted(p.name for p in basetemp.iterdir())
    missing = occplug("validate", "--ckpt", str(run / "checkpoints" / "last.ckpt"))
    assert missing.returncode == 2 and "Traceback" not in missing.stderr
    assert missing.stderr.strip() == (
        f"error: checkpoint {run / 'checkpoints' / 'last.ckpt'} needs plugin 'example' (occplug-example 0.1.0) for "
        "model.heads.occupancy: head 'tiny_mlp', which is not installed; pip install occplug-example==0.1.0"
    )
