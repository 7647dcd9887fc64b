"""The synthetic world as a ``torch.utils.data.Dataset`` of :class:`~occplug.data.Frame`, cached on disk."""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import torch
from torch.utils.data import Dataset
from tqdm.auto import tqdm

from occplug.data.frame import Frame
from occplug.data.records import read_frame, save_frame
from occplug.errors import UserError

from .config import SyntheticWorldConfig
from .frames import generate_frame
from .world import Scene, build_scene

__all__ = ["SyntheticDataset", "default_cache_dir", "generation_workers"]

#: Below this many missing frames the world is generated in this process (starting workers costs seconds).
PARALLEL_MIN_FRAMES = 24


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
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        self.cache_root = None if self.cache_dir is None else self.cache_dir / config.cache_key() / self.split
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

    def pregenerate(self, progress: bool = True, workers: int | None = None) -> int:
        """Generate and cache every frame not cached yet (no-op without a cache); returns the count.

        With ``workers > 1`` (default :func:`generation_workers`) whole scenes go to that many
        processes, one torch thread each; a frame is a pure function of its key and comes out
        bit-identical whatever the thread count, so the cache does not depend on ``workers``.
        """
        if self.cache_root is None:
            return 0
        todo = [divmod(i, self.frames_per_scene) for i in range(len(self))]
        todo = [(s, f) for s, f in todo if not self.cache_path(s, f).is_file()]  # type: ignore[union-attr]
        workers = generation_workers() if workers is None else max(1, int(workers))
        bar = tqdm(total=len(todo), desc=f"synthetic world ({self.split})", unit="frame",
                   disable=not progress or not todo)
        with bar:
            if workers == 1 or len(todo) < PARALLEL_MIN_FRAMES:
                for scene, frame_index in todo:
                    self.frame(scene, frame_index)
                    bar.update()
                return len(todo)
            by_scene: dict[int, list[int]] = {}
            for scene, frame_index in todo:
                by_scene.setdefault(scene, []).append(frame_index)
            # spawn, not fork: a forked child of a process that has run torch's thread pool can hang
            context = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(max_workers=min(workers, len(by_scene)), mp_context=context) as pool:
                jobs = [
                    pool.submit(_generate_scene, self.config, self.split, self.cache_dir, scene, frames)
                    for scene, frames in by_scene.items()
                ]
                for job in as_completed(jobs):
                    bar.update(job.result())
        return len(todo)


def generation_workers() -> int:
    """Processes for :meth:`SyntheticDataset.pregenerate`: ``$OCCPLUG_WORLD_WORKERS``, else the usable CPUs."""
    value = os.environ.get("OCCPLUG_WORLD_WORKERS", "").strip()
    if value:
        if not value.isdigit() or int(value) < 1:
            raise UserError(f"OCCPLUG_WORLD_WORKERS: expected a whole number >= 1, got {value!r}")
        return int(value)
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


def _generate_scene(config: SyntheticWorldConfig, split: str, cache_dir: Path, scene: int, frames: list[int]) -> int:
    """Worker of :meth:`SyntheticDataset.pregenerate`: generate and cache ``frames`` of ``scene``."""
    torch.set_num_threads(1)
    dataset = SyntheticDataset(config, split, cache_dir=cache_dir, with_adjacent=False)
    for frame_index in frames:
        dataset.frame(scene, frame_index)
    return len(frames)
