"""What keeps a run directory whole: one writer at a time, paths that stay inside it, signals that end in a
checkpoint, temporary files that do not outlive their writer.

* :func:`run_lock`: an advisory ``fcntl.flock`` on the run folder itself, held while a fit writes the directory; a
  second process gets one line. The kernel drops the lock when its process dies (SIGKILL too), so a crashed run
  leaves nothing held, and no lock file sits in the run directory.
* :func:`confined_checkpoint_node`: the config's ``checkpoint:`` node, with every path kept inside
  ``<run>/checkpoints``.
* :class:`SignalCheckpoint` and :func:`interruptible`: SIGTERM or SIGINT during ``fit`` saves ``last.ckpt`` after
  the optimizer step in progress and ends with :class:`~.checkpoints.RunInterrupted` (exit ``128 + signum``); a
  second signal stops at once (the last checkpoint on disk stays the one to resume from).
* :func:`remove_stale_temporaries`: the ``.<name>.<pid>.<random>.tmp`` files an atomic write leaves when its process
  is killed mid-write, removed by the next write of that file.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import signal
import threading
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from lightning.pytorch.callbacks import Callback

from occplug.config import ConfigError, read_config
from occplug.run.checkpoints import RunError, RunInterrupted, WriteError

__all__ = [
    "SignalCheckpoint",
    "check_fresh_run_dir",
    "confined_checkpoint_node",
    "interruptible",
    "is_empty_run_dir",
    "read_run_config",
    "remove_stale_temporaries",
    "run_lock",
    "temporary_prefix",
]

#: The signals a fit turns into a last checkpoint and a non-zero exit.
SIGNALS = (signal.SIGTERM, signal.SIGINT)


def is_empty_run_dir(run_dir: Path) -> bool:
    """Whether ``run_dir`` is absent or empty."""
    run_dir = Path(run_dir)
    return not run_dir.exists() or not any(run_dir.iterdir())


def check_fresh_run_dir(run_dir: Path) -> None:
    """Refuse to start a new run in a folder that holds anything.

    Raises:
        RunError: one line naming the folder and the two ways on.
    """
    if not is_empty_run_dir(run_dir):
        raise RunError(
            f"run directory {run_dir} already exists and is not empty; choose another --run-dir or --resume it"
        )


@contextlib.contextmanager
def run_lock(run_dir: Path) -> Iterator[None]:
    """Hold the run directory's advisory lock (creating the folder if needed) for the body.

    The lock is ``flock`` on the folder itself (no lock file: the run directory's contents stay what the run
    writes); the kernel drops it when its process ends, so a crashed run never leaves it held.

    Raises:
        RunError: another live process holds it (one line).
    """
    run_dir = Path(run_dir)
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(run_dir, os.O_RDONLY | os.O_DIRECTORY)
    except OSError as exc:
        raise WriteError(f"cannot write in run directory {run_dir}: {exc.strerror or exc}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        raise RunError(
            f"run directory {run_dir} is in use by another occplug process; wait for it to end, or choose another "
            "--run-dir"
        ) from None
    try:
        yield
    finally:
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


def confined_checkpoint_node(node: Mapping[str, Any] | None) -> dict[str, Any]:
    """The ``checkpoint:`` config node (``ModelCheckpoint`` arguments) with its paths checked: ``dirpath`` is the
    run's own (``<run>/checkpoints``, not settable) and ``filename`` must name a file below it.

    Raises:
        RunError: ``checkpoint.dirpath`` set, or a ``checkpoint.filename`` that is absolute or climbs out with
            ``..`` (one line naming the key and value).
    """
    node = dict(node or {})
    if node.get("dirpath") is not None:
        raise RunError(
            f"checkpoint.dirpath={node['dirpath']!r}: a run writes its checkpoints to <run-dir>/checkpoints; "
            "remove the key (choose the folder with --run-dir)"
        )
    node.pop("dirpath", None)
    name = node.get("filename")
    if name is not None:
        text = str(name)
        parts = Path(os.path.normpath(text)).parts
        if not text or Path(text).is_absolute() or (parts and parts[0] == "..") or "\0" in text:
            raise RunError(
                f"checkpoint.filename={text!r}: expected a file name inside the run's checkpoints/ folder "
                "(no absolute path, no '..' climbing out)"
            )
    return node


def read_run_config(path: Path) -> dict[str, Any]:
    """A run's saved ``config.yaml`` (read on ``--resume``), as a mapping.

    Read as every config is (:func:`occplug.config.read_config`: YAML 1.2 within limits, no tags).

    Raises:
        RunError: one line naming the file: unreadable, not UTF-8, not YAML (or a tag such as ``!!python/object``),
            an alias bomb, or not a mapping.
    """
    try:
        return read_config(Path(path))
    except ConfigError as exc:
        raise RunError(str(exc)) from None


# ----------------------------------------------------------------------------- temporary files
def temporary_prefix(path: Path) -> str:
    """The prefix of this process's temporary files for ``path``: ``.<name>.<pid>.``."""
    return f".{Path(path).name}.{os.getpid()}."


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def remove_stale_temporaries(path: Path) -> list[Path]:
    """Delete the temporary files of earlier writes of ``path`` whose process is gone; return them.

    A temporary file is ``.<name>.<pid>.<random>.tmp`` (older ones: ``.<name>.<random>.tmp``, without a pid, are
    stale too: no writer of this version makes them). Files of live processes are left alone.
    """
    path = Path(path)
    removed = []
    for tmp in path.parent.glob(f".{path.name}.*.tmp"):
        middle = tmp.name[len(path.name) + 2 : -len(".tmp")].split(".")
        if len(middle) == 2 and middle[0].isdigit() and (int(middle[0]) == os.getpid() or _alive(int(middle[0]))):
            continue
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
            removed.append(tmp)
    return removed


# ----------------------------------------------------------------------------- signals
class _HardStop(BaseException):
    """A second SIGTERM / SIGINT: stop where the process is (not caught by ``except Exception``)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


class SignalCheckpoint(Callback):
    """SIGTERM / SIGINT during ``fit``: ``last.ckpt`` after the current optimizer step, then
    :class:`~.checkpoints.RunInterrupted`.

    The checkpoint is written from ``on_train_batch_end``, the hook where ``trainer.checkpoint_every_n_steps``
    writes its own, so a resume from it is as exact as one from a step checkpoint. A signal during validation is
    honoured at the next training step (the validation's own checkpoint is written meanwhile). The handlers are
    (re)installed at ``on_train_start``, after Lightning's own SIGTERM handler, and restored by :func:`interruptible`.

    Args:
        last: the run's ``checkpoints/last.ckpt``.
    """

    def __init__(self, last: Path) -> None:
        self.last = Path(last)
        self.received: int | None = None
        self.saved_step: int | None = None
        self._previous: dict[int, Any] = {}

    def _handler(self, signum: int, frame: Any) -> None:
        if self.received is not None:
            raise _HardStop(signum)
        self.received = signum

    def install(self) -> None:
        """Catch :data:`SIGNALS` (a no-op outside the main thread, where Python cannot set handlers)."""
        if threading.current_thread() is not threading.main_thread():
            return
        for signum in SIGNALS:
            self._previous.setdefault(signum, signal.getsignal(signum))
            signal.signal(signum, self._handler)

    def restore(self) -> None:
        """Put back the handlers :meth:`install` replaced."""
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()

    def on_train_start(self, trainer: Any, pl_module: Any) -> None:
        self.install()

    def on_train_batch_end(self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, batch_idx: int) -> None:
        if self.received is None:
            return
        trainer.save_checkpoint(str(self.last))
        self.saved_step = trainer.global_step
        raise RunInterrupted(self.received, self.status(trainer.global_step, saved=True))

    def status(self, step: int | None, saved: bool) -> str:
        """The status line's middle: the signal, the step, the checkpoint to resume from."""
        name = signal.Signals(self.received or signal.SIGTERM).name
        where = f" at step {step}" if step is not None else ""
        if saved:
            return f"{name}{where}; saved {self.last}"
        if self.last.is_file():
            return f"{name}{where}; the last checkpoint is {self.last}"
        return f"{name}{where}; no checkpoint written yet (a resume starts the run again)"


@contextlib.contextmanager
def interruptible(guard: SignalCheckpoint) -> Iterator[None]:
    """Run the body (a ``trainer.fit``) with ``guard``'s handlers; a signal before training starts, or a second
    one, ends in :class:`~.checkpoints.RunInterrupted` without a new checkpoint."""
    from lightning.pytorch.utilities.exceptions import SIGTERMException

    guard.install()
    try:
        yield
    except _HardStop as stop:
        guard.received = stop.signum
        raise RunInterrupted(stop.signum, guard.status(None, saved=False)) from None
    except SIGTERMException:  # Lightning's own SIGTERM handling (a signal before on_train_start)
        guard.received = guard.received or signal.SIGTERM
        raise RunInterrupted(int(guard.received), guard.status(None, saved=False)) from None
    finally:
        guard.restore()
