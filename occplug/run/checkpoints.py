"""The run's user-facing errors and the one safe way a checkpoint file is read (both re-exported by :mod:`.runner`).

They sit below :mod:`.runner` so that :mod:`.weights`, which :func:`.runner.fit` calls, can use them without an
import circle. Every checkpoint the project reads -- ``validate``/``test``/``predict``/``viz``/``export``, a phase's
weights, and ``fit --resume`` (Lightning is handed this loader through
:class:`~occplug.run.runner.AtomicCheckpointIO`) -- goes through :func:`load_checkpoint`, which passes
``weights_only=True`` explicitly: torch's ``TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD`` (and the ``False`` default of torch
2.4 / 2.5) cannot turn it off.
"""

from __future__ import annotations

import pickle
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from occplug.errors import UserError

__all__ = ["RunError", "RunInterrupted", "WriteError", "check_resume_checkpoint", "load_checkpoint"]


class RunError(Exception):
    """A user-facing problem with a run (exit code 2 from the CLI)."""


class WriteError(RunError, UserError):
    """A run file that cannot be written (disk full, read-only folder, a folder where the file goes); one line
    naming the file, and the previous version is kept. A :class:`~occplug.errors.UserError` too, so every command
    that writes through :func:`occplug.run.runner.write_text_atomic` reports it as one ``error:`` line."""


class RunInterrupted(Exception):
    """A fit stopped by SIGTERM or SIGINT (after its last checkpoint); the CLI exits ``128 + signum``.

    Attributes:
        signum: the signal number.
        message: the status line (which signal, the step, the checkpoint, how to continue).
    """

    def __init__(self, signum: int, message: str) -> None:
        super().__init__(message)
        self.signum = signum
        self.message = message

    @property
    def exit_code(self) -> int:
        """``128 + signum`` (143 for SIGTERM, 130 for SIGINT), as a shell reports a signalled process."""
        return 128 + self.signum


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def load_checkpoint(path: Path) -> dict[str, Any]:
    """Read a checkpoint with ``weights_only=True`` (always passed explicitly, whatever torch's default).

    Raises:
        RunError: one line for a missing file, a truncated or corrupt one, one that holds pickled objects beyond
            tensors and plain data (never unpickled), or one that is not a dict.
    """
    path = Path(path)
    if not path.is_file():
        raise RunError(f"checkpoint {path} does not exist")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        if not zipfile.is_zipfile(path) or "weights only" not in str(exc).lower():  # text, random bytes
            raise RunError(f"checkpoint {path} is truncated or corrupt (not a torch.save file)") from None
        raise RunError(
            f"checkpoint {path} holds objects other than tensors and plain data, which weights_only=True refuses "
            "to unpickle (a foreign or unsafe file); not loaded"
        ) from None
    except (EOFError, zipfile.BadZipFile) as exc:
        raise RunError(f"checkpoint {path} is truncated or corrupt: {_first_line(exc)}") from None
    except Exception as exc:  # noqa: BLE001 (torch's reader raises RuntimeError, KeyError, ... on damaged files)
        text = _first_line(exc)
        if "zip archive" in text or "central directory" in text or isinstance(exc, (KeyError, IndexError)):
            raise RunError(f"checkpoint {path} is truncated or corrupt (not a whole torch.save file)") from None
        raise RunError(f"checkpoint {path} cannot be read safely (weights_only=True): {text}") from None
    if not isinstance(data, dict):
        raise RunError(f"checkpoint {path} holds a {type(data).__name__}, not a checkpoint dict")
    return data


#: Entries every checkpoint Lightning writes during ``fit`` carries, which ``--resume`` needs.
RESUME_KEYS = ("state_dict", "loops", "optimizer_states", "global_step", "epoch")


def check_resume_checkpoint(ckpt: Mapping[str, Any], path: Path, model_state: Mapping[str, torch.Tensor]) -> None:
    """Check, before a resumed run writes anything, that ``ckpt`` is a full occplug training checkpoint of this
    model: Lightning's training state (:data:`RESUME_KEYS`), occplug's run record, and a ``state_dict`` with the
    model's keys and shapes (``model_state``, the freshly built model's ``state_dict()``).

    Raises:
        RunError: one line naming the file and what is wrong.
    """
    missing = [k for k in RESUME_KEYS if k not in ckpt]
    if missing:
        raise RunError(
            f"checkpoint {path} is not a training checkpoint written by occplug fit (no {', '.join(missing)}); "
            "--resume needs the run's own last.ckpt"
        )
    info = ckpt.get("occplug")
    if not isinstance(info, dict) or not isinstance(info.get("config"), dict):
        raise RunError(f"checkpoint {path} carries no occplug run record; --resume needs the run's own last.ckpt")
    state = ckpt["state_dict"]
    if not isinstance(state, Mapping):
        raise RunError(f"checkpoint {path}: state_dict is a {type(state).__name__}, not a mapping of tensors")
    absent = sorted(set(model_state) - set(state))
    extra = sorted(set(state) - set(model_state))
    if absent or extra:
        shown = f"missing {absent[0]}" if absent else f"unexpected {extra[0]}"
        raise RunError(
            f"checkpoint {path} does not match the configured model ({len(absent)} weights missing, "
            f"{len(extra)} unexpected; {shown}); resume with the run's own config"
        )
    for key, want in model_state.items():
        got = state[key]
        if not isinstance(got, torch.Tensor) or tuple(got.shape) != tuple(want.shape):
            shape = tuple(got.shape) if isinstance(got, torch.Tensor) else type(got).__name__
            raise RunError(
                f"checkpoint {path}: {key} has shape {shape}, the configured model {tuple(want.shape)}; "
                "resume with the run's own config"
            )
