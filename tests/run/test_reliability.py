"""Issue 57: resume that is always safe, signals, one writer per run directory, and failing disks.

Every refusal is one ``error:`` line with exit code 2 that leaves the run directory as it was; SIGTERM / SIGINT end
with a checkpoint and ``128 + signum``. One tiny fit (module fixture) is copied for each case.
"""

from __future__ import annotations

import errno
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from occplug.cli import main
from occplug.run import rundir, runner
from occplug.run.checkpoints import RunError, load_checkpoint
from occplug.run.runner import AtomicCheckpointIO, write_text_atomic
from occplug.testing import TINY_FIT

ROOT = Path(__file__).resolve().parents[2]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
#: One epoch of 2 steps on the tiny world, a checkpoint after every step (occplug.testing.TINY_FIT).
TINY = list(TINY_FIT)


class Payload:
    """Unpickling this creates ``path`` (what an attacker's checkpoint would do, harmlessly)."""

    def __init__(self, path: Path) -> None:
        self.path = str(path)

    def __reduce__(self):
        return (exec, (f"open({self.path!r}, 'w').close()",))


def tree(folder: Path) -> dict[str, tuple[int, int]]:
    """``{relative path: (size, mtime_ns)}`` of every file under ``folder``."""
    return {
        str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.rglob("*") if p.is_file()
    }


def one_error(capsys) -> str:
    """The single ``error:`` line the command printed (asserted single, and no traceback)."""
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("reliability") / "run"
    assert main(["fit", "-c", BASELINE, *TINY, "--run-dir", str(run)]) == 0
    return run


@pytest.fixture
def run_copy(finished_run, tmp_path) -> Path:
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    return run


# ----------------------------------------------------------------------------- 1. one safe loader
def test_a_pickled_payload_never_runs_on_resume_even_when_torch_is_forced(run_copy, tmp_path, monkeypatch, capsys):
    """With TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD=1 (torch 2.4/2.5's default behaviour) a plain ``torch.load`` runs the
    payload; ``fit --resume`` (our loader, and Lightning's reads through AtomicCheckpointIO) does not."""
    marker = tmp_path / "marker"
    last = run_copy / "checkpoints" / "last.ckpt"
    ckpt = torch.load(last, weights_only=True)
    torch.save({**ckpt, "extra": Payload(marker)}, last)
    monkeypatch.setenv("TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD", "1")
    before = tree(run_copy)

    assert main(["fit", "--resume", str(run_copy), "trainer.max_epochs=2"]) == 2
    assert "weights_only=True refuses" in one_error(capsys)
    assert not marker.exists()
    with pytest.raises(RunError):  # the path Lightning takes for ckpt_path, whatever weights_only it passes
        AtomicCheckpointIO().load_checkpoint(last, weights_only=False)
    assert not marker.exists()
    assert tree(run_copy) == before  # no logs/version_1, config.yaml not rewritten

    with pytest.warns(UserWarning):  # the control: the forcing variable does make an unqualified load unsafe
        torch.load(last)
    assert marker.exists()


def test_lightning_reads_the_resume_checkpoint_through_the_safe_loader(run_copy, monkeypatch, capsys):
    """``--resume`` reads ``last.ckpt`` once, with ``weights_only=True``: the checkpoint it checked is the one
    Lightning restores (handed over through AtomicCheckpointIO, not read again by Lightning's own loader)."""
    calls = []
    real = torch.load

    def recording(f, *args, **kwargs):
        if str(f).endswith(".ckpt"):
            calls.append((Path(f).name, kwargs.get("weights_only")))
        return real(f, *args, **kwargs)

    monkeypatch.setattr(torch, "load", recording)
    assert main(["fit", "--resume", str(run_copy), "trainer.max_epochs=2"]) == 0
    capsys.readouterr()
    assert calls == [("last.ckpt", True)]


@pytest.mark.parametrize(
    "override, expected",
    [
        ("checkpoint.filename=../../escaped", "checkpoint.filename='../../escaped'"),
        ("checkpoint.filename=/tmp/escaped", "checkpoint.filename='/tmp/escaped'"),
        ("checkpoint.dirpath=/tmp/elsewhere", "checkpoint.dirpath"),  # not a key a config may set
    ],
)
def test_checkpoint_paths_stay_inside_the_run_directory(tmp_path, capsys, override, expected):
    run = tmp_path / "a" / "b" / "run"
    assert main(["fit", "-c", BASELINE, *TINY, override, "--run-dir", str(run)]) == 2
    assert one_error(capsys).startswith(f"error: {expected}")
    assert list(tmp_path.rglob("*")) == []  # nothing written, not even the run directory


def test_a_checkpoint_file_name_below_checkpoints_is_allowed():
    assert rundir.confined_checkpoint_node({"filename": "best/{epoch}"}) == {"filename": "best/{epoch}"}


# ----------------------------------------------------------------------------- 4. resume checks first
def _truncate(run: Path) -> None:
    last = run / "checkpoints" / "last.ckpt"
    last.write_bytes(last.read_bytes()[:2000])


def _foreign(run: Path) -> None:
    torch.save({"state_dict": {"w": torch.zeros(3)}}, run / "checkpoints" / "last.ckpt")


def _other_model(run: Path) -> None:
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)
    ckpt["state_dict"] = {k: v[..., :1] if v.ndim else v for k, v in ckpt["state_dict"].items()}
    torch.save(ckpt, run / "checkpoints" / "last.ckpt")


def _config(text: bytes):
    return lambda run: (run / "config.yaml").write_bytes(text)


@pytest.mark.parametrize(
    "damage, expected",
    [
        (_truncate, "is truncated or corrupt"),
        (_foreign, "is not a training checkpoint written by occplug fit"),
        (_other_model, "has shape"),
        (lambda run: (run / "checkpoints" / "last.ckpt").write_text("not a checkpoint"), "truncated or corrupt"),
        (_config(b"seed: [1, 2\n"), "line 2: invalid YAML"),
        (_config(b"seed: \xff\xfe\n"), "not UTF-8 text"),
        (_config(b"seed: !!python/object/apply:os.system ['true']\n"), "is not allowed"),
        (_config(b"- a list\n"), "must be a mapping at the top level, got list"),
    ],
    ids=["truncated", "foreign", "other-model", "text-file", "bad-yaml", "not-utf8", "python-tag", "not-mapping"],
)
def test_resume_checks_the_checkpoint_and_config_before_writing_anything(run_copy, capsys, damage, expected):
    damage(run_copy)
    before = tree(run_copy)
    assert main(["fit", "--resume", str(run_copy), "trainer.max_epochs=2"]) == 2
    assert expected in one_error(capsys)
    assert tree(run_copy) == before


def test_resume_with_an_override_that_changes_the_model_is_refused_first(run_copy, capsys):
    before = tree(run_copy)
    assert main(["fit", "--resume", str(run_copy), "model.encoder.out_channels=8"]) == 2
    assert "encoder.neck.weight has shape (64, 64, 1, 1), the configured model (8, 64, 1, 1)" in one_error(capsys)
    assert tree(run_copy) == before


# ----------------------------------------------------------------------------- 3. one writer, signals, .tmp
def test_a_second_fit_into_a_locked_run_directory_is_one_error(tmp_path, capsys):
    """Another process holds the run directory (as a running fit does): the second gets one line, exit 2."""
    run = tmp_path / "run"
    code = f"import sys, time; from occplug.run.rundir import run_lock\nwith run_lock({str(run)!r}):\n"
    code += "    print('locked', flush=True); time.sleep(120)\n"
    holder = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        assert main(["fit", "-c", BASELINE, *TINY, "--run-dir", str(run)]) == 2
        assert "is in use by another occplug process" in one_error(capsys)
        assert list(run.iterdir()) == []  # nothing of the second run written (the lock is on the folder itself)
        holder.send_signal(signal.SIGKILL)  # a crashed holder: the kernel drops its lock
        holder.wait()
        with rundir.run_lock(run):
            pass
    finally:
        if holder.poll() is None:
            holder.kill()
            holder.wait()


def _signal_at_step(monkeypatch, signum: int, step: int, times: int = 1) -> None:
    """Send ``signum`` to this process (``times`` times) when training step ``step`` starts."""

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.global_step == step:
            for _ in range(times):
                os.kill(os.getpid(), signum)

    monkeypatch.setattr(rundir.SignalCheckpoint, "on_train_batch_start", on_train_batch_start, raising=False)


@pytest.mark.parametrize("signum, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_saves_a_checkpoint_exits_non_zero_and_resume_finishes(tmp_path, monkeypatch, capsys, signum, code):
    run = tmp_path / "run"
    _signal_at_step(monkeypatch, signum, step=0)
    before = signal.getsignal(signum)
    assert main(["fit", "-c", BASELINE, *TINY, "--run-dir", str(run)]) == code
    err = capsys.readouterr().err
    name = signal.Signals(signum).name
    assert f"interrupted: {name} at step 1; saved {run / 'checkpoints' / 'last.ckpt'}" in err
    assert f"continue with: occplug fit --resume {run}" in err and "Traceback" not in err
    assert signal.getsignal(signum) == before  # the handlers are put back
    assert load_checkpoint(run / "checkpoints" / "last.ckpt")["global_step"] == 1
    assert not (run / "metrics.json").exists()
    monkeypatch.undo()
    assert main(["fit", "--resume", str(run)]) == 0
    capsys.readouterr()
    assert load_checkpoint(run / "checkpoints" / "last.ckpt")["global_step"] == 2


def test_a_second_signal_stops_at_once_without_a_new_checkpoint(tmp_path, monkeypatch, capsys):
    run = tmp_path / "run"
    _signal_at_step(monkeypatch, signal.SIGTERM, step=1, times=2)
    assert main(["fit", "-c", BASELINE, *TINY, "--run-dir", str(run)]) == 143
    err = capsys.readouterr().err
    assert "interrupted: SIGTERM; the last checkpoint is" in err and "Traceback" not in err
    assert load_checkpoint(run / "checkpoints" / "last.ckpt")["global_step"] == 1


def test_sigterm_to_a_fit_process_exits_143_with_a_checkpoint(tmp_path):
    """The real thing: SIGTERM from outside, mid-fit (Lightning's bare SystemExit used to make this exit 0)."""
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "occplug.cli", "fit", "-c", BASELINE, *TINY, "trainer.max_epochs=50"]
    proc = subprocess.Popen([*cmd, "--run-dir", str(run)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        while not (run / "checkpoints" / "last.ckpt").exists():
            assert proc.poll() is None and time.monotonic() < deadline, "no checkpoint"
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 143, err
    assert "interrupted: SIGTERM at step" in err and "Traceback" not in err
    load_checkpoint(run / "checkpoints" / "last.ckpt")


def test_stale_temporary_files_are_removed_by_the_next_write(tmp_path):
    target = tmp_path / "last.ckpt"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = [tmp_path / f".last.ckpt.{dead.pid}.k3j2.tmp", tmp_path / ".last.ckpt.x8y2q1.tmp"]
    live = tmp_path / f".last.ckpt.{os.getppid()}.a1b2.tmp"  # a live writer's (our parent's pid)
    other = tmp_path / ".config.yaml.1.zz.tmp"
    for p in [*stale, live, other]:
        p.write_bytes(b"partial")
    AtomicCheckpointIO().save_checkpoint({"w": torch.ones(2)}, target)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["last.ckpt", live.name, other.name])


# ----------------------------------------------------------------------------- 7. disks and caches
def test_a_full_disk_during_a_checkpoint_write_is_one_error_and_keeps_the_old_one(run_copy, monkeypatch, capsys):
    last = run_copy / "checkpoints" / "last.ckpt"
    old = last.read_bytes()

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(runner.os, "fsync", full)
    assert main(["fit", "--resume", str(run_copy), "trainer.max_epochs=2"]) == 2
    line = one_error(capsys)
    assert "cannot write" in line and "No space left on device" in line
    assert last.read_bytes() == old
    assert not [p for p in run_copy.rglob("*.tmp")]


def test_a_read_only_run_directory_is_one_error(tmp_path, monkeypatch, capsys):
    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(rundir.os, "open", read_only)  # the run directory's first write is its lock
    assert main(["fit", "-c", BASELINE, *TINY, "--run-dir", str(tmp_path / "run")]) == 2
    assert "cannot write in run directory" in one_error(capsys)


@pytest.mark.parametrize("case", ["file-root", "folder-entry", "read-only"])
def test_cache_problems_are_one_error(tmp_path, monkeypatch, capsys, case):
    from occplug.data import records

    cache = tmp_path / "cache"
    if case == "file-root":
        cache.write_text("not a folder")
        expected = "is a file, not a folder"
    elif case == "folder-entry":  # the first training frame's cache file is a folder
        monkeypatch.setenv("OCCPLUG_CACHE", str(cache))
        dm = runner.build_datamodule(runner.load_config([BASELINE], TINY))
        (dm.cache_dir / dm.world_config.cache_key() / "train" / "0000-000.pt").mkdir(parents=True)
        expected = "a folder is in the way"
    else:

        def read_only(*args, **kwargs):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))

        monkeypatch.setattr(records.tempfile, "mkstemp", read_only)
        expected = "Read-only file system"
    monkeypatch.setenv("OCCPLUG_CACHE", str(cache))
    run = tmp_path / "run"
    assert main(["fit", "-c", BASELINE, *TINY, "data.num_workers=0", "--run-dir", str(run)]) == 2
    line = one_error(capsys)
    assert "cannot write cache entry" in line and expected in line, line
    assert not run.exists()


def test_write_text_atomic_reports_a_folder_in_the_way(tmp_path):
    (tmp_path / "metrics.json").mkdir()
    with pytest.raises(runner.WriteError, match=r"metrics.json: a folder is in the way"):
        write_text_atomic(tmp_path / "metrics.json", "{}")
