"""Where the pictures' samples come from: a config's data set and, optionally, a checkpoint.

:class:`SampleSource` builds the data module of a resolved config (``runner.build_datamodule``)
and, given a checkpoint, the model (``runner.build_model`` + the checkpoint's weights), so
``occplug viz`` sees exactly the frames and predictions that ``occplug validate`` would.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterator
from functools import cached_property
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from occplug.data.frame import Frame, collate_frames
from occplug.data.sequences import SceneIndex
from occplug.geometry import GridSpec
from occplug.run import runner

from .style import Palette

__all__ = ["SampleSource", "SourceError"]

SPLITS = ("train", "val", "test", "predict")
_CACHED_FRAMES = 4  # frames kept by SampleSource.frame (a decoded frame can be hundreds of MB)


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
        self._frames: OrderedDict[int, Frame] = OrderedDict()
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

    def _checked(self, index: int) -> int:
        """``index`` in ``[0, len)`` (negative indices count from the end); SourceError when out of range."""
        n = len(self)
        if not -n <= index < n:
            raise SourceError(f"--index {index} is out of range: the {self.split} split has {n} samples")
        return index % n

    def load(self, index: int) -> Frame:
        """Item ``index`` of the split, decoded afresh unless recently used, and not kept (for
        streaming long sequences)."""
        index = self._checked(index)
        cached = self._frames.get(index)
        return cached if cached is not None else self.dataset[index]

    def frame(self, index: int) -> Frame:
        """Item ``index`` of the split (negative indices count from the end); the last few are kept."""
        index = self._checked(index)
        if index in self._frames:
            self._frames.move_to_end(index)
        else:
            self._frames[index] = self.dataset[index]
            while len(self._frames) > _CACHED_FRAMES:
                self._frames.popitem(last=False)
        return self._frames[index]

    @torch.no_grad()
    def predict(self, frame: Frame) -> Tensor | None:
        """``(X, Y, Z)`` int64 predicted class ids for ``frame``, or None without a checkpoint."""
        if self.model is None:
            return None
        batch = collate_frames([frame]).to(self.model.device)
        return self.model.predict_occupancy(batch)[0].cpu()

    @cached_property
    def scenes(self) -> SceneIndex | None:
        """The split's scene structure without decoding a frame, or None when the data set has none.

        The readers' data sets (and a pipelined synthetic one) carry a ``scenes``
        :class:`~occplug.data.sequences.SceneIndex`; the bare synthetic data set is scene-major with
        ``frames_per_scene`` frames in each of its ``num_scenes`` scenes.
        """
        scenes = getattr(self.dataset, "scenes", None)
        if isinstance(scenes, SceneIndex):
            return scenes
        per_scene, count = getattr(self.dataset, "frames_per_scene", None), getattr(self.dataset, "num_scenes", None)
        if isinstance(per_scene, int) and isinstance(count, int) and per_scene > 0 and per_scene * count == len(self):
            return SceneIndex.regular([f"scene {s}" for s in range(count)], per_scene)
        return None

    def sequence(self, index: int) -> list[int]:
        """Indices of every frame of ``index``'s scene, in time order.

        Read from :attr:`scenes` where the data set has a scene structure; otherwise (a data set laid
        out scene-major, as every occplug data module is) found by decoding the frames outwards from
        ``index`` while the scene name stays the same, one at a time, keeping only their scene names
        and frame numbers.
        """
        index = self._checked(index)
        if self.scenes is not None:
            return list(self.scenes.items[self.scenes.locate(index)[0]])
        scene = self.frame(index).scene
        order = {index: self.frame(index).frame_index}
        for step in (-1, 1):
            i = index + step
            while 0 <= i < len(self):
                frame = self.load(i)
                if frame.scene != scene:
                    break
                order[i] = frame.frame_index
                i += step
        return sorted(order, key=lambda i: (order[i], i))

    def stream(self, indices: list[int]) -> Iterator[Frame]:
        """The frames of ``indices`` one at a time, each decoded when it is asked for and not kept."""
        for i in indices:
            yield self.load(i)
