"""Where the pictures' samples come from: a config's data set and, optionally, a checkpoint.

:class:`SampleSource` builds the data module of a resolved config (``runner.build_datamodule``)
and, given a checkpoint, the model (``runner.build_model`` + the checkpoint's weights), so
``occplug viz`` sees exactly the frames and predictions that ``occplug validate`` would.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from occplug import runner
from occplug.data.frame import Frame, collate_frames
from occplug.geometry import GridSpec

from .style import Palette

__all__ = ["SampleSource", "SourceError"]

SPLITS = ("train", "val", "test", "predict")


class SourceError(ValueError):
    """A user-facing problem: bad split, index out of range, model/data mismatch."""


class SampleSource:
    """Frames of one split and the model's predictions for them.

    Args:
        cfg: a resolved, validated config (``runner.load_config`` / ``resolve_run_config``).
        split: ``train``, ``val``, ``test`` or ``predict``.
        ckpt_path: a checkpoint whose weights predict occupancy, or None for ground truth only.

    Attributes:
        grid: the label grid (``Frame.voxel_labels`` and predictions live on it).
        palette: the data set's class colours.
    """

    def __init__(self, cfg: dict[str, Any], split: str = "val", ckpt_path: Path | None = None) -> None:
        if split not in SPLITS:
            raise SourceError(f"--split {split}: expected one of {', '.join(SPLITS)}")
        try:
            self.dm = runner.build_datamodule(cfg)
            self.dataset = self.dm.dataset(split)
        except (ValueError, TypeError, FileNotFoundError) as exc:
            raise SourceError(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None
        self.split = split
        self.grid: GridSpec = self.dm.grid
        self.palette = Palette.from_datamodule(self.dm)
        self.model: Any = None
        self._frames: dict[int, Frame] = {}
        if ckpt_path is not None:
            self.model = self._load_model(cfg, Path(ckpt_path))

    def _load_model(self, cfg: dict[str, Any], path: Path) -> Any:
        ckpt = runner.load_checkpoint(path)
        try:
            model = runner.build_model(cfg, self.dm)
            model.load_state_dict(ckpt["state_dict"])
        except (KeyError, RuntimeError, ValueError, TypeError) as exc:
            raise SourceError(
                f"checkpoint {path} does not match the configured model: {str(exc).splitlines()[0]}"
            ) from None
        model_grid = getattr(model, "grid", self.grid)
        if tuple(model_grid.shape) != tuple(self.grid.shape):
            raise SourceError(f"the model predicts on a {model_grid.shape} grid, the labels are on {self.grid.shape}")
        return model.eval()

    def __len__(self) -> int:
        return len(self.dataset)  # type: ignore[arg-type]

    def frame(self, index: int) -> Frame:
        """Item ``index`` of the split (negative indices count from the end)."""
        n = len(self)
        if not -n <= index < n:
            raise SourceError(f"--index {index} is out of range: the {self.split} split has {n} samples")
        index %= n
        if index not in self._frames:
            if len(self._frames) > 64:
                self._frames.clear()
            self._frames[index] = self.dataset[index]
        return self._frames[index]

    @torch.no_grad()
    def predict(self, frame: Frame) -> Tensor | None:
        """``(X, Y, Z)`` int64 predicted class ids for ``frame``, or None without a checkpoint."""
        if self.model is None:
            return None
        batch = collate_frames([frame]).to(self.model.device)
        return self.model.predict_occupancy(batch)[0].cpu()

    def sequence(self, index: int) -> list[int]:
        """Indices of every frame of ``index``'s scene, in time order.

        Data sets laid out scene-major (every occplug data module) are walked outwards from
        ``index`` while the scene name stays the same.
        """
        self.frame(index)
        index %= len(self)
        scene = self.frame(index).scene
        first = index
        while first > 0 and self.frame(first - 1).scene == scene:
            first -= 1
        last = index
        while last + 1 < len(self) and self.frame(last + 1).scene == scene:
            last += 1
        order = sorted(range(first, last + 1), key=lambda i: (self.frame(i).frame_index, i))
        return order
