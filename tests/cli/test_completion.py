"""``occplug completion bash|zsh``: the generated script completes commands, options, config references,
override keys and ``type=`` names, in the shell itself (issue 56 item 6)."""

from __future__ import annotations

import contextlib
import io
import shutil
import subprocess
from pathlib import Path

import pytest

from occplug.cli import main
from occplug.plugins import config_dirs, get_registry

SHELLS = ["bash", pytest.param("zsh", marks=pytest.mark.skipif(shutil.which("zsh") is None, reason="no zsh"))]


@pytest.fixture(scope="module")
def scripts(tmp_path_factory) -> dict[str, Path]:
    out = {}
    folder = tmp_path_factory.mktemp("completion")
    for shell in ("bash", "zsh"):
        buffer = io.StringIO()
        with contextlib.redirect_stdout(buffer):
            assert main(["completion", shell]) == 0
        out[shell] = folder / f"occplug.{shell}"
        out[shell].write_text(buffer.getvalue())
    return out


def _complete(shell: str, script: Path, line: str, cwd: Path) -> list[str]:
    program = (
        f'source "{script}"; COMP_LINE="$1"; COMP_POINT=${{#COMP_LINE}}; _occplug_complete; '
        'for w in "${COMPREPLY[@]}"; do echo "$w"; done'
    )
    done = subprocess.run(
        [shell, "-c", program, shell, line], capture_output=True, text=True, cwd=cwd, timeout=60, check=False
    )
    assert done.returncode == 0 and not done.stderr, done.stderr
    return done.stdout.splitlines()


@pytest.mark.parametrize("shell", SHELLS)
def test_the_script_completes_commands_options_refs_keys_and_types(shell, scripts, tmp_path):
    registry = get_registry()
    script = scripts[shell]
    assert _complete(shell, script, "occplug con", tmp_path) == ["config"]
    assert _complete(shell, script, "occplug config ", tmp_path) == ["show", "validate"]
    assert _complete(shell, script, "occplug config show --def", tmp_path) == ["--defaults"]
    assert _complete(shell, script, "occplug comp", tmp_path) == ["completion"]
    encoders = [n for n in registry.names("encoder") if n.startswith("s")]
    assert encoders and _complete(shell, script, "occplug fit -c x model.encoder.type=s", tmp_path) == encoders
    heads = list(registry.names("head"))
    assert _complete(shell, script, "occplug fit -c x model.heads.occupancy.type=", tmp_path) == heads
    assert _complete(shell, script, "occplug fit -c x data.type=", tmp_path) == list(registry.names("data"))
    keys = _complete(shell, script, "occplug config show -c x model.encoder.", tmp_path)
    assert "model.encoder.out_channels=" in keys and "model.encoder.type=" in keys
    assert _complete(shell, script, "occplug fit -c x model.vi", tmp_path) == ["model.view_transform."]
    assert _complete(shell, script, "occplug fit -c x gr", tmp_path) == ["grid="]
    folder = Path(config_dirs()["queryocc"])
    refs = sorted(f"queryocc/{p.relative_to(folder).with_suffix('').as_posix()}" for p in folder.rglob("*.yaml"))
    assert sorted(_complete(shell, script, "occplug fit -c queryocc/", tmp_path)) == refs
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "mine.yaml").write_text("seed: 1\n")
    assert "configs/mine.yaml" in _complete(shell, script, "occplug fit -c conf", tmp_path)
    assert _complete(shell, script, "occplug config validate -c mi", tmp_path) == ["mine.yaml"]


def test_an_unknown_shell_is_one_error_line(capsys):
    assert main(["completion", "fish"]) == 2
    assert capsys.readouterr().err == "error: completion fish: unknown shell; expected one of bash, zsh\n"
