"""The synthetic world as a ``torch.utils.data.Dataset`` of :class:`~occplug.data.Frame`, cached on disk."""

from __future__ import annotations

import os
from pathlib import Path

from torch.utils.data import Dataset
from tqdm.auto import tqdm

from occplug.data.frame import Frame
from occplug.data.records import read_frame, save_frame

from .config import SyntheticWorldConfig
from .frames import generate_frame
from .world import Scene, build_scene

__all__ = ["SyntheticDataset", "default_cache_dir"]


def default_cache_dir() -> Path:
    """``$OCCPLUG_CACHE/synthetic`` if ``OCCPLUG_CACHE`` is set, else ``~/.cache/occplug/synthetic``."""
    root = os.environ.get("OCCPLUG_CACHE")
    return (Path(root) if root else Path.home() / ".cache" / "occplug") / "synthetic"


class SyntheticDataset(Dataset[Frame]):
    """Every frame of one split, scene-major: item ``i`` is frame ``i % F`` of scene ``i // F``.

    A frame is a pure function of ``(config, split, scene, frame)``, so it is generated on first
    access and, with a ``cache_dir``, stored as
    ``cache_dir / config.cache_key() / split / "{scene:04d}-{frame:03d}.pt"`` (written atomically);
    later accesses, in any process, read that file.

    ``Frame.adjacent[k]`` holds the frame ``frame_index + k`` of the same scene for every
    ``k`` in ``config.adjacent_offsets``, **clamped** to the scene's first/last frame at its ends
    (so ``adjacent[-1]`` of frame 0 is frame 0 itself; its pose, timestamp and token say so).
    Adjacent frames carry no adjacent frames of their own.

    Args:
        config: the world.
        split: ``train``, ``val`` or ``test`` (``predict`` reads ``val``).
        cache_dir: cache root, or None to generate every time.
        with_adjacent: False leaves ``Frame.adjacent`` empty whatever the config says.
    """

    def __init__(self, config: SyntheticWorldConfig, split: str, cache_dir: str | Path | None = None,
                 with_adjacent: bool = True) -> None:
        self.config = config
        self.split = "val" if split == "predict" else split
        self.num_scenes = config.scenes(self.split)
        self.frames_per_scene = config.frames(self.split)
        self.cache_root = None if cache_dir is None else Path(cache_dir) / config.cache_key() / self.split
        self.offsets = tuple(config.adjacent_offsets) if with_adjacent else ()
        self._scenes: dict[int, Scene] = {}

    def __len__(self) -> int:
        return self.num_scenes * self.frames_per_scene

    def locate(self, index: int) -> tuple[int, int]:
        """``(scene, frame)`` of item ``index``."""
        if not 0 <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} {self.split} frames")
        return divmod(index, self.frames_per_scene)

    def __getitem__(self, index: int) -> Frame:
        scene, frame_index = self.locate(index)
        frame = self.frame(scene, frame_index)
        last = self.frames_per_scene - 1
        for k in self.offsets:
            frame.adjacent[k] = self.frame(scene, min(max(frame_index + k, 0), last))
        return frame

    def scene(self, index: int) -> Scene:
        """The generated scene ``index`` (memoised; the last two are kept)."""
        if index not in self._scenes:
            if len(self._scenes) >= 2:
                self._scenes.pop(next(iter(self._scenes)))
            self._scenes[index] = build_scene(self.config, self.split, index)
        return self._scenes[index]

    def cache_path(self, scene: int, frame_index: int) -> Path | None:
        """Where frame ``(scene, frame_index)`` is cached, or None without a cache."""
        return None if self.cache_root is None else self.cache_root / f"{scene:04d}-{frame_index:03d}.pt"

    def frame(self, scene: int, frame_index: int) -> Frame:
        """Frame ``frame_index`` of scene ``scene`` without adjacent frames (cached)."""
        path = self.cache_path(scene, frame_index)
        if path is not None and path.is_file():
            try:
                return read_frame(path)
            except Exception:  # noqa: BLE001 (an unreadable cache entry is regenerated)
                pass
        frame = generate_frame(self.config, self.scene(scene), self.split, scene, frame_index)
        if path is not None:
            save_frame(frame, path)
        return frame

    def pregenerate(self, progress: bool = True) -> int:
        """Generate and cache every frame not cached yet (no-op without a cache); returns the count."""
        if self.cache_root is None:
            return 0
        todo = [divmod(i, self.frames_per_scene) for i in range(len(self))]
        todo = [(s, f) for s, f in todo if not self.cache_path(s, f).is_file()]  # type: ignore[union-attr]
        bar = tqdm(todo, desc=f"synthetic world ({self.split})", unit="frame", disable=not progress or not todo)
        for scene, frame_index in bar:
            self.frame(scene, frame_index)
        return len(todo)
