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
from .frames import frame_token, generate_frame
from .world import Scene, build_scene

__all__ = ["SyntheticDataset", "default_cache_dir", "generation_workers", "pregenerate"]

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

    def __init__(
        self, config: SyntheticWorldConfig, split: str, cache_dir: str | Path | None = None, with_adjacent: bool = True
    ) -> None:
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

    def pregenerate(self, progress: bool = True, workers: int | None = None, pseudo: object | None = None) -> int:
        """Generate and cache every frame not cached yet (no-op without a cache); returns the count.

        See :func:`pregenerate` (this is it for one split).
        """
        return pregenerate([self], progress=progress, workers=workers, pseudo=pseudo)


def pregenerate(
    datasets: list[SyntheticDataset], progress: bool = True, workers: int | None = None, pseudo: object | None = None
) -> int:
    """Generate and cache the missing frames of several splits in one pool; returns the number of frames done.

    With ``workers > 1`` (default :func:`generation_workers`) whole scenes go to that many processes,
    one torch thread each, largest first (one pool for every split: no second start-up, no idle
    worker while the other finishes a split); a frame is a pure function of its key and comes out
    bit-identical whatever the thread count, so the cache does not depend on ``workers``. ``pseudo``
    (a :class:`~.pseudo.SyntheticPseudoLabels` with a ``cache_dir``) also makes and caches the frames'
    pseudo-label maps, in the same pass.
    """
    todo: list[tuple[SyntheticDataset, int, int]] = []
    for ds in datasets:
        if ds.cache_root is None:
            continue
        for i in range(len(ds)):
            scene, frame_index = divmod(i, ds.frames_per_scene)
            if not ds.cache_path(scene, frame_index).is_file() or (  # type: ignore[union-attr]
                pseudo is not None and not pseudo.is_cached(frame_token(ds.config, ds.split, scene, frame_index))
            ):
                todo.append((ds, scene, frame_index))
    if not todo:
        return 0
    workers = generation_workers() if workers is None else max(1, int(workers))
    splits = "/".join(dict.fromkeys(ds.split for ds, _, _ in todo))
    with tqdm(total=len(todo), desc=f"synthetic world ({splits})", unit="frame", disable=not progress) as bar:
        if workers == 1 or len(todo) < PARALLEL_MIN_FRAMES:
            for ds, scene, frame_index in todo:
                _make(ds, scene, frame_index, pseudo)
                bar.update()
            return len(todo)
        jobs: dict[tuple[int, int], list[int]] = {}
        for ds, scene, frame_index in todo:
            jobs.setdefault((datasets.index(ds), scene), []).append(frame_index)
        order = sorted(jobs, key=lambda key: -len(jobs[key]))
        # spawn, not fork: a forked child of a process that has run torch's thread pool can hang
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=min(workers, len(order)), mp_context=context) as pool:
            futures = [
                pool.submit(
                    _generate_scene,
                    datasets[d].config,
                    datasets[d].split,
                    datasets[d].cache_dir,
                    scene,
                    jobs[(d, scene)],
                    pseudo,
                )
                for d, scene in order
            ]
            for job in as_completed(futures):
                bar.update(job.result())
    return len(todo)


def _make(ds: SyntheticDataset, scene: int, frame_index: int, pseudo: object | None) -> None:
    frame = ds.frame(scene, frame_index)
    if pseudo is not None:
        pseudo.maps(frame)  # type: ignore[attr-defined]  (cached by the labeler)


def generation_workers() -> int:
    """Processes for :meth:`SyntheticDataset.pregenerate`: ``$OCCPLUG_WORLD_WORKERS``, else the usable CPUs."""
    value = os.environ.get("OCCPLUG_WORLD_WORKERS", "").strip()
    if value:
        if not value.isdigit() or int(value) < 1:
            raise UserError(f"OCCPLUG_WORLD_WORKERS: expected a whole number >= 1, got {value!r}")
        return int(value)
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


def _generate_scene(
    config: SyntheticWorldConfig,
    split: str,
    cache_dir: Path,
    scene: int,
    frames: list[int],
    pseudo: object | None = None,
) -> int:
    """Worker of :func:`pregenerate`: generate and cache ``frames`` of ``scene`` (and their pseudo maps)."""
    torch.set_num_threads(1)
    dataset = SyntheticDataset(config, split, cache_dir=cache_dir, with_adjacent=False)
    for frame_index in frames:
        _make(dataset, scene, frame_index, pseudo)
    return len(frames)
