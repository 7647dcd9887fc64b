"""Crash-safe runs: a fit killed with SIGKILL mid-epoch resumes to the same weights and metrics as an
uninterrupted one; the loader resumes at its position; run files are written atomically."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import yaml
from torch.utils.data import DistributedSampler

from occplug.cli import main
from occplug.config import ConfigError
from occplug.data.datamodule import ResumableLoader
from occplug.data.sequences import SceneIndex, StreamRunSampler
from occplug.run.runner import AtomicCheckpointIO, load_config, write_json, write_text_atomic

# one pytest-xdist worker runs the whole module (pyproject: --dist loadgroup): the uninterrupted schedules (a module
# fixture) are fitted once
pytestmark = pytest.mark.xdist_group("resume")

ROOT = Path(__file__).resolve().parents[1]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
#: 2 epochs of 2 steps (2 of the tiny world's 6 batches per epoch), a checkpoint after every step.
RUN = [
    "data.preset=tiny",
    "data.num_workers=0",
    "trainer.accelerator=cpu",
    "trainer.deterministic=true",
    "trainer.enable_progress_bar=false",
    "trainer.max_epochs=2",
    "trainer.limit_train_batches=2",
    "trainer.limit_val_batches=1",
    "trainer.checkpoint_every_n_steps=1",
]
STEPS_PER_EPOCH = 2


# ----------------------------------------------------------------------------- the loader
def _collect(loader, count=None):
    out = []
    for batch in loader:
        out.append(batch)
        if count is not None and len(out) == count:
            break
    return out


def test_loader_resumes_at_its_position_and_restores_the_random_state():
    """A pass cut after 2 batches, its state loaded into a fresh loader, yields the remaining batches and
    the very random draws the uninterrupted pass made after them."""

    class Noisy(torch.utils.data.Dataset):
        def __len__(self):
            return 10

        def __getitem__(self, i):
            return torch.tensor([float(i), torch.rand(()).item()])  # an "augmentation" from the global RNG

    def loader():
        return ResumableLoader(Noisy(), batch_size=3, sampler=DistributedSampler(Noisy(), 1, 0, seed=7))

    torch.manual_seed(0)
    whole = loader()
    whole.sampler.set_epoch(1)
    reference = _collect(whole)
    assert len(reference) == 4

    torch.manual_seed(0)
    cut = loader()
    cut.sampler.set_epoch(1)
    first = _collect(cut, 2)
    state = cut.position()
    assert state["batches"] == 2
    torch.manual_seed(123)  # whatever the new process's generator holds
    resumed = loader()
    iter(resumed)  # Lightning makes an iterator before it restores the checkpoint
    resumed.resume_at(state)
    resumed.sampler.set_epoch(1)
    rest = _collect(resumed)
    assert len(rest) == 2 and resumed.batches_done == 4
    for got, want in zip(first + rest, reference, strict=True):
        assert torch.equal(got, want)
    assert len(_collect(resumed)) == 4  # the skip applies once


def test_loader_resume_skips_by_index_without_loading_samples():
    seen = []

    class Counting(torch.utils.data.Dataset):
        def __len__(self):
            return 6

        def __getitem__(self, i):
            seen.append(i)
            return i

    loader = ResumableLoader(Counting(), batch_size=2, shuffle=False)
    loader.resume_at({"batches": 2, "rng": loader.position()["rng"]})
    assert [b.tolist() for b in loader] == [[4, 5]]
    assert seen == [4, 5]


def test_a_stream_sampler_resumes_its_runs_mid_epoch():
    """The sequential training sampler (slots of consecutive frames) resumes through the same loader."""
    scenes = SceneIndex.regular(["a", "b", "c"], 4)

    class Items(torch.utils.data.Dataset):  # reads what the sampler yields (a StreamItem), as StreamDataset does
        def __len__(self):
            return 12

        def __getitem__(self, key):
            return torch.tensor([key.index, int(key.start)])

    def loader():
        sampler = StreamRunSampler(scenes, batch_size=2, run_length=2, num_replicas=1, rank=0, seed=3)
        sampler.set_epoch(2)
        return ResumableLoader(Items(), batch_size=2, sampler=sampler)

    reference = [b.tolist() for b in loader()]
    cut = loader()
    first = [b.tolist() for b in _collect(cut, 3)]
    resumed = loader()
    resumed.resume_at(cut.position())
    assert len(reference) == 6 and first + [b.tolist() for b in resumed] == reference


def test_the_data_module_carries_the_train_loader_position_only_inside_an_epoch():
    """Checkpoints taken mid-epoch carry the loader's position (and the next loader resumes there); one
    taken at the epoch's end carries nothing (the next epoch starts afresh)."""
    from types import SimpleNamespace

    from occplug.run.runner import build_datamodule

    cfg = load_config([BASELINE], ["data.preset=tiny"])
    dm = build_datamodule(cfg)
    dm.trainer = SimpleNamespace(num_training_batches=3)
    assert dm.state_dict() == {}  # no loader yet
    loader = dm.train_dataloader()
    loader.sampler.set_epoch(0)
    it = iter(loader)
    next(it)
    state = dm.state_dict()
    assert state["train_loader"]["batches"] == 1
    next(it), next(it)
    assert dm.state_dict() == {}  # the epoch's 3 batches are done
    fresh = build_datamodule(cfg)
    fresh.load_state_dict(state)
    resumed = fresh.train_dataloader()
    resumed.sampler.set_epoch(0)
    tokens = [b.token for b in resumed]
    loader.sampler.set_epoch(0)
    assert tokens == [b.token for b in loader][1:]


# ----------------------------------------------------------------------------- atomic files
def test_run_files_are_replaced_atomically(tmp_path, monkeypatch):
    """A write that fails midway leaves the previous file whole and no temporary file behind."""
    target = tmp_path / "metrics.json"
    write_json(target, {"mIoU": 1.0})
    real_dumps = json.dumps

    def broken(*args, **kwargs):
        raise KeyboardInterrupt  # e.g. the user's Ctrl-C while writing

    monkeypatch.setattr(json, "dumps", broken)
    with pytest.raises(KeyboardInterrupt):
        write_json(target, {"mIoU": 2.0})
    monkeypatch.setattr(json, "dumps", real_dumps)
    assert json.loads(target.read_text()) == {"mIoU": 1.0}
    write_text_atomic(tmp_path / "config.yaml", "a: 1\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["config.yaml", "metrics.json"]
    mask = os.umask(0)
    os.umask(mask)
    assert (tmp_path / "config.yaml").stat().st_mode & 0o777 == 0o666 & ~mask


def test_checkpoint_io_keeps_the_old_checkpoint_when_saving_fails(tmp_path):
    io = AtomicCheckpointIO()
    path = tmp_path / "checkpoints" / "last.ckpt"
    io.save_checkpoint({"w": torch.arange(3)}, path)

    class Unpicklable:
        def __reduce__(self):
            raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        io.save_checkpoint({"w": torch.zeros(3), "bad": Unpicklable()}, path)
    assert torch.equal(torch.load(path, weights_only=True)["w"], torch.arange(3))
    assert [p.name for p in path.parent.iterdir()] == ["last.ckpt"]


# ----------------------------------------------------------------------------- the config key
def test_checkpoint_every_n_steps_is_validated():
    assert load_config([BASELINE], ["trainer.checkpoint_every_n_steps=5"])["trainer"]["checkpoint_every_n_steps"] == 5
    with pytest.raises(ConfigError, match=r"trainer.checkpoint_every_n_steps: expected an int >= 1, got int 0"):
        load_config([BASELINE], ["trainer.checkpoint_every_n_steps=0"])
    with pytest.raises(ConfigError, match=r"trainer.checkpoint_every_n_steps: expected"):
        load_config([BASELINE], ["trainer.checkpoint_every_n_steps=often"])


# ----------------------------------------------------------------------------- SIGKILL and resume
def _progress(ckpt: Path) -> tuple[int, int]:
    """``(global step, batches of the current epoch the train loader handed out)`` of a checkpoint."""
    data = torch.load(ckpt, map_location="cpu", weights_only=True)
    return data["global_step"], data["SyntheticDataModule"]["train_loader"]["batches"]


def test_a_run_killed_mid_epoch_resumes_bit_identical(tmp_path, capsys):
    """SIGKILL after the first mid-epoch checkpoint, ``fit --resume``: the same last.ckpt weights and
    metrics.json as an uninterrupted run (which runs meanwhile, in its own process)."""
    killed, whole = tmp_path / "killed", tmp_path / "whole"
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    cmd = [sys.executable, "-c", "import sys; from occplug.cli import main; sys.exit(main())", "fit", "-c", BASELINE]
    quiet = {"env": env, "stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    proc = subprocess.Popen([*cmd, *RUN, "--run-dir", str(killed)], **quiet)
    reference = subprocess.Popen([*cmd, *RUN, "--run-dir", str(whole)], **quiet)
    last = killed / "checkpoints" / "last.ckpt"
    try:
        deadline = time.monotonic() + 240
        while not last.exists():  # the first step's checkpoint: mid-epoch 0
            assert proc.poll() is None, "the run ended before writing its first checkpoint"
            assert time.monotonic() < deadline, "no checkpoint after 240 s"
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
        assert proc.wait() == -signal.SIGKILL
        step, in_epoch = _progress(last)
        assert step % STEPS_PER_EPOCH != 0 and in_epoch == step % STEPS_PER_EPOCH, (step, in_epoch)  # mid-epoch
        assert not (killed / "metrics.json").exists()
        yaml.safe_load((killed / "config.yaml").read_text())  # every run file is whole
        json.loads((killed / "plugins.json").read_text())

        assert main(["fit", "--resume", str(killed)]) == 0
        capsys.readouterr()
        assert reference.wait(timeout=600) == 0
    finally:
        for p in (proc, reference):
            if p.poll() is None:
                p.kill()
                p.wait()

    a = torch.load(killed / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    b = torch.load(whole / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert a["global_step"] == b["global_step"] == 2 * STEPS_PER_EPOCH
    assert a["state_dict"].keys() == b["state_dict"].keys()
    for key in b["state_dict"]:
        assert torch.equal(a["state_dict"][key], b["state_dict"][key]), key
    assert json.loads((killed / "metrics.json").read_text()) == json.loads((whole / "metrics.json").read_text())
    assert (killed / "logs" / "version_1").is_dir()  # the resume logged beside the killed run's log


# ----------------------------------------------------------------------------- a kill right after each write
#: Two schedules that between them write last.ckpt at every kind of point: A validates at each epoch's end and
#: checkpoints every step; B validates mid-epoch (every 2 of 3 steps) with no step checkpoints.
SCHEDULES = {
    "A": RUN,
    "B": [*RUN[:-1], "trainer.limit_train_batches=3", "trainer.val_check_interval=2"],
}


class _Snapshots:
    """Copies of every last.ckpt one uninterrupted fit writes, in order, each labelled with the hook that wrote
    it: a SIGKILL right after a write leaves exactly that file for ``--resume``."""

    def __init__(self, monkeypatch, folder: Path) -> None:
        import shutil
        import traceback

        self.files: list[tuple[str, Path]] = []
        real = AtomicCheckpointIO.save_checkpoint

        def spy(io, checkpoint, path, storage_options=None):
            real(io, checkpoint, path, storage_options)
            if Path(path).name == "last.ckpt":
                hooks = [f.name for f in traceback.extract_stack() if f.name.startswith("on_")]
                hook = hooks[-1] if hooks else "end of fit"
                copy = folder / f"{len(self.files)}.ckpt"
                shutil.copy(path, copy)
                self.files.append((hook, copy))

        monkeypatch.setattr(AtomicCheckpointIO, "save_checkpoint", spy)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """``{schedule: (run dir, [(hook, snapshot)])}``, each schedule fitted once."""
    out = {}
    with pytest.MonkeyPatch.context() as mp:
        for name, overrides in SCHEDULES.items():
            folder = tmp_path_factory.mktemp(f"schedule{name}")
            snaps = _Snapshots(mp, folder)
            assert main(["fit", "-c", BASELINE, *overrides, "--run-dir", str(folder / "run")]) == 0
            mp.undo()
            out[name] = (folder / "run", snaps.files)
    return out


def _resume_from_snapshot(run: Path, snapshot: Path, into: Path) -> dict:
    import shutil

    shutil.copytree(run, into, ignore=shutil.ignore_patterns("*.ckpt", "metrics.json", "logs"))
    (into / "checkpoints").mkdir(exist_ok=True)
    shutil.copy(snapshot, into / "checkpoints" / "last.ckpt")
    assert main(["fit", "--resume", str(into)]) == 0
    return torch.load(into / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)


#: (schedule, index of the write, the hook that makes it); the fast set holds the issue's case (after epoch 0's
#: validation) and a mid-epoch validation; the rest run with -m slow.
POINTS = [
    pytest.param("A", 2, "on_train_epoch_end", id="A-end-of-epoch-0-after-validation"),
    pytest.param("B", 0, "on_validation_end", id="B-validation-mid-epoch"),
    pytest.param("A", 0, "on_train_batch_end", id="A-step-mid-epoch", marks=pytest.mark.slow),
    pytest.param("A", 1, "on_train_batch_end", id="A-step-last-of-epoch", marks=pytest.mark.slow),
    pytest.param("A", 3, "on_train_batch_end", id="A-step-mid-epoch-1", marks=pytest.mark.slow),
    pytest.param("B", 1, "on_validation_end", id="B-validation-mid-epoch-1", marks=pytest.mark.slow),
]


@pytest.mark.parametrize("schedule, index, hook", POINTS)
def test_a_kill_right_after_each_kind_of_checkpoint_write_resumes_bit_identical(
    uninterrupted, tmp_path, capsys, schedule, index, hook
):
    run, snaps = uninterrupted[schedule]
    written_by, snapshot = snaps[index]
    assert written_by == hook, [h for h, _ in snaps]
    got = _resume_from_snapshot(run, snapshot, tmp_path / "resumed")
    capsys.readouterr()
    want = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert got["global_step"] == want["global_step"] > torch.load(snapshot, weights_only=True)["global_step"]
    for key in want["state_dict"]:
        assert torch.equal(got["state_dict"][key], want["state_dict"][key]), key
    assert sorted(p.name for p in (tmp_path / "resumed" / "checkpoints").glob("last*")) == ["last.ckpt"]  # no -v1
    assert json.loads((tmp_path / "resumed" / "metrics.json").read_text()) == json.loads(
        (run / "metrics.json").read_text()
    )
