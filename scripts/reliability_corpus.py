"""Issue 57's adversarial corpus: hostile files, damaged runs, signals, locks, full and read-only disks.

Each case sets something up in its own folder, runs one ``occplug`` command and checks how it ends: exit 2 with
exactly one ``error:`` line (or 0 where success is right, or 143 / 130 with one ``interrupted:`` line for a
signal), no traceback, and nothing half-written (a damaged run directory is left byte for byte as it was; a refused
fit leaves no run directory). Cases run in this process through :func:`occplug.cli.main` (fast); those that need a
process of their own (signals, a second writer, memory bombs) run as subprocesses under a time and memory limit.

    python scripts/reliability_corpus.py            # every case; one line per case, a summary, exit 1 on a failure
    python scripts/reliability_corpus.py --fast     # only the in-process cases (what tests/scripts runs)
    python scripts/reliability_corpus.py --list     # the cases and their kinds

A case whose fix belongs to another part of issue 57 (YAML limits and finite numbers: item 5; evaluation
refusals: item 6) is marked ``pending``: its failure is reported as ``PENDING``, not as a failure, and its pass
as ``FIXED`` (then drop the mark).
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from unittest import mock

from occplug.testing import TINY_FIT

ROOT = Path(__file__).resolve().parents[1]
BASELINE = str(ROOT / "configs" / "baseline.yaml")
#: One epoch of 2 steps on the tiny world, a checkpoint after every step (occplug.testing.TINY_FIT).
TINY = list(TINY_FIT)
FIT = ["fit", "-c", BASELINE, *TINY]


@dataclass
class Ctx:
    """What a case's setup gets: its own folder, a copy of a finished tiny run on request, and patches."""

    folder: Path
    base_run: Path | None
    patches: list[Any] = field(default_factory=list)
    env: dict[str, str] = field(default_factory=dict)
    watched: Path | None = None  # a folder that must end as it began (byte for byte)
    absent: list[Path] = field(default_factory=list)  # paths that must not exist afterwards

    def run_copy(self) -> Path:
        assert self.base_run is not None
        run = self.folder / "run"
        shutil.copytree(self.base_run, run)
        return run

    def patch(self, target: str, value: Any) -> None:
        self.patches.append(mock.patch(target, value))

    def write(self, name: str, data: str | bytes) -> Path:
        path = self.folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data.encode() if isinstance(data, str) else data)
        return path


@dataclass
class Case:
    name: str
    kind: str
    setup: Callable[[Ctx], list[str]]
    expect: int = 2
    message: str = ""  # a part of the one error / interrupted line
    needs_run: bool = False
    process: bool = False  # run in a subprocess (signals, bombs, second writers)
    pending: str = ""  # the issue-57 item that fixes it, when not this one
    timeout: float = 300.0  # seconds, for a subprocess case


def _raise(err: int) -> Callable[..., Any]:
    def fail(*args: Any, **kwargs: Any) -> Any:
        raise OSError(err, os.strerror(err))

    return fail


# ----------------------------------------------------------------------------- cases: security
class _Payload:
    def __init__(self, path: Path) -> None:
        self.path = str(path)

    def __reduce__(self) -> Any:
        return (exec, (f"open({self.path!r}, 'w').close()",))


def _payload_ckpt(ctx: Ctx, path: Path) -> Path:
    import torch

    base = torch.load(ctx.base_run / "checkpoints" / "last.ckpt", weights_only=True)  # type: ignore[operator]
    marker = ctx.folder / "PAYLOAD_RAN"
    ctx.absent.append(marker)
    torch.save({**base, "extra": _Payload(marker)}, path)
    ctx.env["TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD"] = "1"  # what torch 2.4 / 2.5 do by default
    return path


def resume_payload(ctx: Ctx) -> list[str]:
    run = ctx.run_copy()
    _payload_ckpt(ctx, run / "checkpoints" / "last.ckpt")
    ctx.watched = run
    return ["fit", "--resume", str(run), "trainer.max_epochs=2"]


def validate_payload(ctx: Ctx) -> list[str]:
    return ["validate", "--ckpt", str(_payload_ckpt(ctx, ctx.folder / "evil.ckpt"))]


def predict_payload(ctx: Ctx) -> list[str]:
    ctx.absent.append(ctx.folder / "out")
    return ["predict", "--ckpt", str(_payload_ckpt(ctx, ctx.folder / "evil.ckpt")), "--out", str(ctx.folder / "out")]


def fit_with(*overrides: str) -> Callable[[Ctx], list[str]]:
    def setup(ctx: Ctx) -> list[str]:
        run = ctx.folder / "a" / "b" / "run"
        ctx.absent += [ctx.folder / "a", ctx.folder / "escaped"]
        return [*FIT, *overrides, "--run-dir", str(run)]

    return setup


# ----------------------------------------------------------------------------- cases: resume
def damaged(change: Callable[[Path], None], *overrides: str) -> Callable[[Ctx], list[str]]:
    def setup(ctx: Ctx) -> list[str]:
        run = ctx.run_copy()
        change(run)
        ctx.watched = run
        return ["fit", "--resume", str(run), *overrides]

    return setup


def _last(run: Path) -> Path:
    return run / "checkpoints" / "last.ckpt"


def _truncate(run: Path) -> None:
    _last(run).write_bytes(_last(run).read_bytes()[:4096])


def _foreign(run: Path) -> None:
    import torch

    torch.save({"state_dict": {"w": torch.zeros(3)}}, _last(run))


def _no_record(run: Path) -> None:
    import torch

    ckpt = torch.load(_last(run), weights_only=True)
    del ckpt["occplug"]
    torch.save(ckpt, _last(run))


def _halved(run: Path) -> None:
    import torch

    ckpt = torch.load(_last(run), weights_only=True)
    ckpt["state_dict"] = {k: v[..., :1] if v.ndim else v for k, v in ckpt["state_dict"].items()}
    torch.save(ckpt, _last(run))


def _config(data: bytes) -> Callable[[Path], None]:
    return lambda run: (run / "config.yaml").write_bytes(data)


def _stale_tmp(ctx: Ctx) -> list[str]:
    run = ctx.run_copy()
    stale = run / "checkpoints" / ".last.ckpt.999999999.k3j2.tmp"  # a killed writer's (no such pid)
    stale.write_bytes(b"half a checkpoint")
    ctx.absent.append(stale)
    return ["fit", "--resume", str(run), "trainer.max_epochs=2"]


# ----------------------------------------------------------------------------- cases: one writer
def locked(ctx: Ctx) -> list[str]:
    """The run folder flock-ed as a running fit holds it (another open file description conflicts as another
    process's would)."""
    import fcntl

    run = ctx.folder / "run"
    run.mkdir(parents=True)
    fd = os.open(run, os.O_RDONLY | os.O_DIRECTORY)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    ctx.patches.append(contextlib.closing(_Releaser(fd)))
    return [*FIT, "--run-dir", str(run)]


class _Releaser:
    def __init__(self, fd: int) -> None:
        self.fd = fd

    def close(self) -> None:
        os.close(self.fd)  # closing the last descriptor drops the flock


def _fit_until(run: Path, written: Path) -> subprocess.Popen:
    """A tiny fit of 3 epochs into ``run`` in its own process, returned once it has written ``written``."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "occplug.cli", *FIT, "trainer.max_epochs=3", "--run-dir", str(run)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 240
    while not written.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    return proc


def two_processes(ctx: Ctx) -> list[str]:
    """Two ``fit`` processes into one --run-dir, started together: the second is refused."""
    run = ctx.folder / "run"
    first = _fit_until(run, run / "config.yaml")
    ctx.patches.append(contextlib.closing(_Killer(first)))
    return [*FIT, "--run-dir", str(run)]


class _Killer:
    def __init__(self, proc: subprocess.Popen) -> None:
        self.proc = proc

    def close(self) -> None:
        self.proc.kill()
        self.proc.wait()


# ----------------------------------------------------------------------------- cases: disks and caches
def full_disk(ctx: Ctx) -> list[str]:
    run = ctx.run_copy()
    ctx.patch("torch.save", _raise(errno.ENOSPC))  # the checkpoint's bytes (config.yaml is written before)
    ctx.watched = run / "checkpoints"
    return ["fit", "--resume", str(run), "trainer.max_epochs=2"]


def read_only_run_dir(ctx: Ctx) -> list[str]:
    ctx.patch("occplug.run.rundir.os.open", _raise(errno.EROFS))
    return [*FIT, "--run-dir", str(ctx.folder / "run")]


def cache_is_file(ctx: Ctx) -> list[str]:
    ctx.env["OCCPLUG_CACHE"] = str(ctx.write("cache", "a file"))
    ctx.absent.append(ctx.folder / "run")
    return [*FIT, "--run-dir", str(ctx.folder / "run")]


def cache_entry_folder(ctx: Ctx) -> list[str]:
    from occplug.run import runner

    cache = ctx.folder / "cache"
    with mock.patch.dict(os.environ, {"OCCPLUG_CACHE": str(cache)}):
        dm = runner.build_datamodule(runner.load_config([BASELINE], TINY))
        (dm.cache_dir / dm.world_config.cache_key() / "train" / "0000-000.pt").mkdir(parents=True)  # type: ignore[operator]
    ctx.env["OCCPLUG_CACHE"] = str(cache)
    ctx.absent.append(ctx.folder / "run")
    return [*FIT, "--run-dir", str(ctx.folder / "run")]


def cache_read_only(ctx: Ctx) -> list[str]:
    ctx.env["OCCPLUG_CACHE"] = str(ctx.folder / "cache")
    ctx.patch("occplug.data.records.tempfile.mkstemp", _raise(errno.EROFS))
    ctx.absent.append(ctx.folder / "run")
    return [*FIT, "--run-dir", str(ctx.folder / "run")]


def json_into_folder(ctx: Ctx) -> list[str]:
    (ctx.folder / "out.json").mkdir()
    return ["validate", "--ckpt", str(_last(ctx.base_run)), "--json", str(ctx.folder / "out.json")]  # type: ignore[arg-type]


def metrics_full_disk(ctx: Ctx) -> list[str]:
    ctx.patch("occplug.run.runner.os.fsync", _raise(errno.ENOSPC))
    return ["validate", "--ckpt", str(_last(ctx.base_run)), "--json", str(ctx.folder / "m.json")]  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- cases: configs (item 5)
def config_file(text: str | bytes, *command: str) -> Callable[[Ctx], list[str]]:
    def setup(ctx: Ctx) -> list[str]:
        path = ctx.write("bad.yaml", text)
        ctx.env["CORPUS_LIMIT_AS_GB"] = "6"  # a bomb ends in MemoryError, not in a swapping machine
        return [*(command or ("config", "show")), "-c", str(path)]

    return setup


ALIAS_BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{c}: &{c} [{', '.join(['*' + p] * 9)}]\n" for p, c in zip("abcdefgh", "bcdefghi", strict=True)
)
INTERPOLATION_BOMB = "x0: aaaaaaaaaaaaaaaa\n" + "".join(f"x{i}: ${{x{i - 1}}}${{x{i - 1}}}\n" for i in range(1, 34))


# ----------------------------------------------------------------------------- cases: evaluation (item 6)
def eval_tree(gt_value: int | None = None, pred_value: int = 0, nan_origin: bool = False):
    def setup(ctx: Ctx) -> list[str]:
        import numpy as np

        # written as a user's own tools write them: Occ3D's labels.npz and one <token>.npz (key "pred") per sample
        labels = np.full((40, 40, 8), 17, dtype=np.uint8)
        labels[:, :, 0] = 11 if gt_value is None else gt_value
        mask = np.ones((40, 40, 8), dtype=np.uint8)
        (ctx.folder / "gt" / "gts" / "scene-0" / "t0").mkdir(parents=True)
        np.savez(
            ctx.folder / "gt" / "gts" / "scene-0" / "t0" / "labels.npz",
            semantics=labels,
            mask_lidar=mask,
            mask_camera=mask,
        )
        pred = labels.copy() if gt_value is None else np.full_like(labels, 17)
        pred[0, 0, 0] = pred_value if pred_value else pred[0, 0, 0]
        (ctx.folder / "pred").mkdir(parents=True)
        np.savez(ctx.folder / "pred" / "t0.npz", pred=pred)
        extra = []
        if nan_origin:
            np.savez(ctx.folder / "origins.npz", t0=np.full((1, 3), np.nan, dtype=np.float32))
            extra = ["--metric", "rayiou", "--origins", str(ctx.folder / "origins.npz")]
        grid = ["--grid", "-16", "-16", "-1", "16", "16", "5.4", "--voxel-size", "0.8"]
        return [
            "eval",
            "--gt",
            str(ctx.folder / "gt"),
            "--pred",
            str(ctx.folder / "pred"),
            "--split",
            "all",
            *grid,
            *extra,
        ]

    return setup


# ----------------------------------------------------------------------------- cases: signals
def signalled(signum: int) -> Callable[[Ctx], list[str]]:
    def setup(ctx: Ctx) -> list[str]:
        ctx.env["CORPUS_SIGNAL_AFTER_CHECKPOINT"] = str(int(signum))
        return [*FIT, "trainer.max_epochs=50", "--run-dir", str(ctx.folder / "run")]

    return setup


def killed_then_resumed(ctx: Ctx) -> list[str]:
    run = ctx.folder / "run"
    proc = _fit_until(run, _last(run))
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    return ["fit", "--resume", str(run)]


CASES = [
    # security
    Case("resume-pickled-payload-forced", "security", resume_payload, message="weights_only=True", needs_run=True),
    Case("validate-pickled-payload", "security", validate_payload, message="weights_only=True", needs_run=True),
    Case("predict-pickled-payload", "security", predict_payload, message="weights_only=True", needs_run=True),
    Case("checkpoint-filename-dotdot", "security", fit_with("checkpoint.filename=../../escaped"), message=".."),
    Case("checkpoint-filename-absolute", "security", fit_with("checkpoint.filename=/tmp/corpus-escaped")),
    Case("checkpoint-dirpath", "security", fit_with("checkpoint.dirpath=/tmp/corpus-elsewhere"), message="dirpath"),
    # resume
    Case("resume-truncated", "resume", damaged(_truncate), message="truncated", needs_run=True),
    Case("resume-foreign", "resume", damaged(_foreign), message="not a training checkpoint", needs_run=True),
    Case("resume-no-run-record", "resume", damaged(_no_record), message="no occplug run record", needs_run=True),
    Case("resume-other-model", "resume", damaged(_halved), message="has shape", needs_run=True),
    Case("resume-text-ckpt", "resume", damaged(lambda r: _last(r).write_text("x")), needs_run=True),
    Case("resume-empty-ckpt", "resume", damaged(lambda r: _last(r).write_bytes(b"")), needs_run=True),
    Case("resume-ckpt-is-folder", "resume", damaged(lambda r: (_last(r).unlink(), _last(r).mkdir())), needs_run=True),
    Case("resume-no-ckpt", "resume", damaged(lambda r: _last(r).unlink()), message="no checkpoint", needs_run=True),
    Case("resume-no-config", "resume", damaged(lambda r: (r / "config.yaml").unlink()), needs_run=True),
    Case("resume-config-invalid-yaml", "resume", damaged(_config(b"seed: [1, 2\n")), message="YAML", needs_run=True),
    Case("resume-config-not-utf8", "resume", damaged(_config(b"seed: \xff\xfe\n")), message="UTF-8", needs_run=True),
    Case(
        "resume-config-python-tag",
        "resume",
        damaged(_config(b"a: !!python/object/apply:os.system [id]\n")),
        needs_run=True,
    ),
    Case(
        "resume-config-a-list",
        "resume",
        damaged(_config(b"- 1\n")),
        message="must be a mapping at the top level",
        needs_run=True,
    ),
    Case("resume-config-typo", "resume", damaged(_config(b"sed: 0\n")), needs_run=True),
    Case(
        "resume-override-other-model", "resume", damaged(lambda r: None, "model.encoder.out_channels=8"), needs_run=True
    ),
    Case("resume-missing-dir", "resume", lambda ctx: ["fit", "--resume", str(ctx.folder / "nope")]),
    Case("resume-a-file", "resume", lambda ctx: ["fit", "--resume", str(ctx.write("f", "x"))]),
    Case("resume-healthy", "resume", damaged(lambda r: None, "trainer.max_epochs=2"), expect=0, needs_run=True),
    Case("resume-removes-stale-tmp", "resume", _stale_tmp, expect=0, needs_run=True),
    # one writer, signals
    Case("fit-into-locked-run-dir", "concurrency", locked, message="in use by another occplug process"),
    Case("fit-into-non-empty-dir", "concurrency", lambda ctx: [*FIT, "--run-dir", str(ctx.write("run/x", "x").parent)]),
    Case("two-fits-one-run-dir", "concurrency", two_processes, message="run directory", process=True),
    Case("sigterm-mid-fit", "signals", signalled(signal.SIGTERM), expect=143, message="SIGTERM at step", process=True),
    Case("sigint-mid-fit", "signals", signalled(signal.SIGINT), expect=130, message="SIGINT at step", process=True),
    Case("sigkill-then-resume", "signals", killed_then_resumed, expect=0, process=True),
    # disks and caches
    Case("checkpoint-write-disk-full", "disk", full_disk, message="No space left on device", needs_run=True),
    Case("run-dir-read-only", "disk", read_only_run_dir, message="cannot write in run directory"),
    Case("run-dir-is-a-file", "disk", lambda ctx: [*FIT, "--run-dir", str(ctx.write("f", "x"))]),
    Case("run-dir-below-a-file", "disk", lambda ctx: [*FIT, "--run-dir", str(ctx.write("f", "x") / "run")]),
    Case("cache-path-is-a-file", "disk", cache_is_file, message="is a file, not a folder"),
    Case("cache-entry-is-a-folder", "disk", cache_entry_folder, message="a folder is in the way"),
    Case("cache-read-only", "disk", cache_read_only, message="Read-only file system"),
    Case("json-output-is-a-folder", "disk", json_into_folder, needs_run=True),
    Case("metrics-json-disk-full", "disk", metrics_full_disk, message="No space left", needs_run=True),
    # configs (item 5)
    Case("config-invalid-yaml", "config", config_file("a: [1, 2\n")),
    Case("config-not-utf8", "config", config_file(b"a: \xff\n")),
    Case("config-python-tag", "config", config_file("a: !!python/object/apply:os.system [id]\n")),
    Case(
        "config-unknown-key",
        "config",
        lambda ctx: ["config", "validate", "-c", BASELINE, "model.encoder.out_chanels=3"],
    ),
    Case(
        "config-out-channels-zero",
        "config",
        lambda ctx: ["config", "validate", "-c", BASELINE, "model.encoder.out_channels=0"],
    ),
    Case("config-alias-bomb", "config", config_file(ALIAS_BOMB), process=True, timeout=60),
    Case("config-interpolation-bomb", "config", config_file(INTERPOLATION_BOMB), process=True, timeout=60),
    Case("config-lr-inf", "config", lambda ctx: ["config", "validate", "-c", BASELINE, "optimizer.lr=.inf"]),
    Case(
        "config-seed-beyond-64-bits",
        "config",
        lambda ctx: ["config", "validate", "-c", BASELINE, "seed=18446744073709551617"],
    ),
    # evaluation (item 6)
    Case("eval-gt-id-outside-taxonomy", "eval", eval_tree(gt_value=40)),
    Case("eval-pred-id-out-of-range", "eval", eval_tree(pred_value=200)),
    Case("eval-nan-origins", "eval", eval_tree(nan_origin=True)),
]


# ----------------------------------------------------------------------------- running
@dataclass
class Outcome:
    case: Case
    code: int | None
    err: str
    problems: list[str]
    seconds: float

    @property
    def verdict(self) -> str:
        if self.case.pending:
            return "FIXED" if not self.problems else "PENDING"
        return "ok" if not self.problems else "FAIL"


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _judge(case: Case, ctx: Ctx, code: int | None, err: str, before: dict[str, bytes] | None) -> list[str]:
    problems = []
    if code != case.expect:
        problems.append(f"exit {code}, expected {case.expect}")
    if "Traceback" in err:
        problems.append("traceback")
    prefix = {2: "error:", 143: "interrupted:", 130: "interrupted:"}.get(case.expect)
    lines = [line for line in err.splitlines() if line.startswith(("error:", "interrupted:"))]
    if prefix is None and any(line.startswith("error:") for line in lines):
        problems.append("an error line on success")
    if prefix is not None and [line[: len(prefix)] for line in lines] != [prefix]:
        problems.append(f"{len(lines)} error/interrupted lines, expected one {prefix!r}")
    if case.message and prefix is not None and not any(case.message in line for line in lines):
        problems.append(f"the line lacks {case.message!r}")
    if case.expect != 0 and before is not None and ctx.watched is not None and _tree(ctx.watched) != before:
        problems.append(f"{ctx.watched} changed")
    problems += [f"{p} exists" for p in ctx.absent if p.exists()]
    return problems


@contextlib.contextmanager
def _applied(ctx: Ctx) -> Iterator[None]:
    with contextlib.ExitStack() as stack:
        stack.enter_context(mock.patch.dict(os.environ, ctx.env))
        for patch in ctx.patches:
            stack.enter_context(patch)
        yield


def _in_process(argv: list[str], ctx: Ctx) -> tuple[int | None, str]:
    from occplug.cli import main

    err, out = io.StringIO(), io.StringIO()
    with _applied(ctx), contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            code: int | None = main(argv)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
        except BaseException:  # noqa: BLE001 (an escaped exception is what the corpus looks for)
            err.write(traceback.format_exc())
            code = None
    return code, err.getvalue()


#: The child of a subprocess case: a memory limit (config cases), then the CLI (and, for the signal cases, a signal to itself
#: once the first checkpoint is written).
CHILD = """
import os, resource, signal, sys
limit = int(os.environ.get("CORPUS_LIMIT_AS_GB", "0")) << 30
if limit:
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
after = os.environ.get("CORPUS_SIGNAL_AFTER_CHECKPOINT")
if after:
    from occplug.run import runner
    real = runner.AtomicCheckpointIO.save_checkpoint
    sent = []
    def spy(io, checkpoint, path, storage_options=None):
        real(io, checkpoint, path, storage_options)
        if not sent:  # once: a second signal would stop the run at once, by design
            sent.append(1)
            os.kill(os.getpid(), int(after))
    runner.AtomicCheckpointIO.save_checkpoint = spy
from occplug.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _subprocess(argv: list[str], ctx: Ctx, timeout: float) -> tuple[int | None, str]:
    with contextlib.ExitStack() as stack:
        for patch in ctx.patches:  # closers (a first process to stop afterwards)
            stack.enter_context(patch)
        try:
            proc = subprocess.run(
                [sys.executable, "-c", CHILD, *argv],
                env={**os.environ, **ctx.env},
                capture_output=True,
                text=True,
                timeout=timeout,
            )
        except subprocess.TimeoutExpired:
            return None, f"timed out after {timeout:.0f} s"
    return proc.returncode, proc.stderr


def base_run(folder: Path) -> Path:
    """A finished tiny run every ``needs_run`` case copies."""
    from occplug.cli import main

    run = folder / "base-run"
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert main([*FIT, "--run-dir", str(run)]) == 0, "the corpus's base run failed"
    return run


def run_cases(cases: list[Case], folder: Path, timeout: float = 300.0, echo: bool = True) -> list[Outcome]:
    """Run ``cases`` under ``folder``; return their outcomes (printed one line each when ``echo``)."""
    shared = base_run(folder) if any(c.needs_run for c in cases) else None
    outcomes = []
    for case in cases:
        ctx = Ctx(folder / case.name, shared)
        ctx.folder.mkdir(parents=True)
        start = time.monotonic()
        try:
            argv = case.setup(ctx)
            before = _tree(ctx.watched) if ctx.watched is not None else None
            code, err = _subprocess(argv, ctx, min(timeout, case.timeout)) if case.process else _in_process(argv, ctx)
            problems = _judge(case, ctx, code, err, before)
        except Exception:  # noqa: BLE001 (a broken setup is a failed case, not a stopped corpus)
            code, err, problems = None, traceback.format_exc(), ["setup failed"]
        outcome = Outcome(case, code, err, problems, time.monotonic() - start)
        outcomes.append(outcome)
        if echo:
            shown = "; ".join(problems) if problems else (err.strip().splitlines() or [""])[-1][:100]
            print(f"{outcome.verdict:7s} {case.kind:11s} {case.name:34s} {outcome.seconds:5.1f}s  {shown}", flush=True)
    return outcomes


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fast", action="store_true", help="only the in-process cases")
    parser.add_argument("--list", action="store_true", help="list the cases")
    parser.add_argument("-k", metavar="TEXT", help="only cases whose name contains TEXT")
    parser.add_argument("--json", metavar="FILE", help="also write the outcomes as JSON")
    args = parser.parse_args(argv)
    cases = [c for c in CASES if not (args.fast and c.process) and (not args.k or args.k in c.name)]
    if args.list:
        for c in cases:
            print(f"{c.kind:11s} {c.name:34s} exit {c.expect}{'  (subprocess)' if c.process else ''}  {c.pending}")
        return 0
    with tempfile.TemporaryDirectory(prefix="occplug-corpus-") as tmp:
        outcomes = run_cases(cases, Path(tmp))
    counts = {v: sum(o.verdict == v for o in outcomes) for v in ("ok", "FAIL", "PENDING", "FIXED")}
    print(f"{len(outcomes)} cases: " + ", ".join(f"{n} {v}" for v, n in counts.items()))
    if args.json:
        Path(args.json).write_text(
            json.dumps(
                [
                    {
                        "case": o.case.name,
                        "kind": o.case.kind,
                        "verdict": o.verdict,
                        "exit": o.code,
                        "problems": o.problems,
                        "pending": o.case.pending,
                    }
                    for o in outcomes
                ],
                indent=1,
            )
            + "\n"
        )
    return 1 if counts["FAIL"] else 0


if __name__ == "__main__":
    sys.exit(main())
