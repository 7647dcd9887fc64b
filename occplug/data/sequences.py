"""Sequences: scenes in temporal order, adjacent frames, and a sampler that streams whole scenes.

Every occplug data set is a list of frames in **scene-major temporal order**: the items of one
scene are contiguous or at least ordered by time, and :class:`SceneIndex` records which items
form each scene. On top of that this module gives every reader the same two things:

* **Adjacent frames** (:meth:`SceneIndex.neighbour`): a sample can carry the frames ``k`` steps
  before or after it in its scene (``Frame.adjacent[k]``). Offsets are **clamped** at the scene's
  ends, as the synthetic world does: ``adjacent[-1]`` of a scene's first frame is that frame itself
  (its token, timestamp and pose say so). :func:`relative_motion` gives the ego motion between a
  frame and one of its adjacent frames.
* **Stream samplers** (``data.sequential: true``). Training (:class:`StreamRunSampler`): every
  batch slot of every rank plays its own runs of consecutive frames (scenes cut into runs of
  ``run_length`` frames, shuffled per epoch), with the geometric augmentation drawn once per run
  and ``is_sequence_start`` set at every run start. Evaluation (:class:`SceneEvalSampler`): whole
  scenes per rank, dealt to lanes, every frame exactly once (no padding) also under DDP and with
  batch > 1. :class:`StreamDataset` reads what they yield. ``Frame.extras["is_sequence_start"]``
  (set by the readers: the first frame of its scene) becomes ``Batch.is_sequence_start``: a
  stream state (:class:`occplug.streams.StreamState`) resets there.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
import torch.distributed as dist
from torch import Tensor
from torch.utils.data import Dataset, DistributedSampler

from occplug.geometry import relative_pose

from .frame import Frame

__all__ = [
    "SceneEvalSampler",
    "SceneIndex",
    "StreamDataset",
    "StreamItem",
    "StreamRunSampler",
    "partition_scenes",
    "relative_motion",
    "split_runs",
    "stream_sampler",
]


@dataclass(frozen=True)
class SceneIndex:
    """Which data-set items form each scene, in temporal order.

    Attributes:
        names: scene names, one per scene.
        items: per scene, the data-set indices of its frames in temporal order.
    """

    names: tuple[str, ...]
    items: tuple[tuple[int, ...], ...]

    def __post_init__(self) -> None:
        where: dict[int, tuple[int, int]] = {}
        for s, members in enumerate(self.items):
            for p, i in enumerate(members):
                if i in where:
                    raise ValueError(f"item {i} belongs to two scenes ({self.names[where[i][0]]}, {self.names[s]})")
                where[i] = (s, p)
        object.__setattr__(self, "_where", where)

    @classmethod
    def from_scene_names(cls, scene_of_item: Sequence[str]) -> SceneIndex:
        """Group items by scene name; items keep their data-set order inside a scene."""
        order: dict[str, list[int]] = {}
        for i, name in enumerate(scene_of_item):
            order.setdefault(name, []).append(i)
        return cls(tuple(order), tuple(tuple(v) for v in order.values()))

    @classmethod
    def regular(cls, names: Sequence[str], frames_per_scene: int) -> SceneIndex:
        """Scenes of ``frames_per_scene`` consecutive items each (the synthetic world's layout)."""
        return cls(
            tuple(names),
            tuple(tuple(range(s * frames_per_scene, (s + 1) * frames_per_scene)) for s in range(len(names))),
        )

    def __len__(self) -> int:
        return len(self.names)

    @property
    def num_items(self) -> int:
        """Total number of items over all scenes."""
        return sum(len(m) for m in self.items)

    def locate(self, index: int) -> tuple[int, int]:
        """``(scene number, position in the scene)`` of data-set item ``index``."""
        try:
            return self._where[index]  # type: ignore[attr-defined]
        except KeyError:
            raise IndexError(f"item {index} is in no scene") from None

    def is_start(self, index: int) -> bool:
        """Whether item ``index`` is the first frame of its scene."""
        return self.locate(index)[1] == 0

    def neighbour(self, index: int, offset: int) -> int:
        """The item ``offset`` frames after ``index`` in its scene, clamped to the scene's ends."""
        scene, pos = self.locate(index)
        members = self.items[scene]
        return members[min(max(pos + offset, 0), len(members) - 1)]


def relative_motion(frame: Frame, offset: int) -> Tensor:
    """``(4, 4)`` float64 pose mapping the ego frame of ``frame.adjacent[offset]`` into ``frame``'s.

    ``T_{g->e}^{cur} T_{e->g}^{adj}`` (DuOcc Eq. 1): a point ``p`` in the adjacent frame's ego frame
    is ``relative_motion(frame, k) @ p`` in the current one.
    """
    if offset not in frame.adjacent:
        raise KeyError(f"frame {frame.token} has no adjacent frame {offset:+d} (has: {sorted(frame.adjacent)})")
    return relative_pose(frame.adjacent[offset].ego_to_global.double(), frame.ego_to_global.double())


def partition_scenes(lengths: Sequence[int], parts: int) -> list[list[int]]:
    """Split scenes (given their lengths, in order) into ``parts`` contiguous groups of similar total length.

    Group ``g`` ends where the running total comes closest to ``(g + 1) / parts`` of the whole,
    while leaving at least one scene for every group. With no more scenes than parts, group ``g``
    holds scene ``g`` alone and the last groups are empty.

    Returns:
        ``parts`` lists of scene numbers.
    """
    n = len(lengths)
    if n <= parts:
        return [[g] if g < n else [] for g in range(parts)]
    prefix = [0.0]
    for length in lengths:
        prefix.append(prefix[-1] + length)
    bounds = [0]
    for g in range(1, parts):
        lo, hi = bounds[-1] + 1, n - (parts - g)  # every group keeps at least one scene
        target = prefix[-1] * g / parts
        bounds.append(min(range(lo, hi + 1), key=lambda j: (abs(prefix[j] - target), j)))
    bounds.append(n)
    return [list(range(bounds[g], bounds[g + 1])) for g in range(parts)]


def split_runs(scenes: SceneIndex, run_length: int | None = None) -> list[tuple[int, ...]]:
    """Cut every scene into runs of consecutive frames (the units a training slot streams).

    A scene of ``n`` frames becomes ``ceil(n / run_length)`` runs of near-equal length (they differ
    by at most one frame; DuOcc cuts each nuScenes scene in two); ``None`` keeps whole scenes.
    """
    if run_length is not None and run_length < 1:
        raise ValueError(f"data.sequential.run_length must be >= 1 or null, got {run_length}")
    runs: list[tuple[int, ...]] = []
    for members in scenes.items:
        n = len(members)
        if n == 0:
            continue
        k = 1 if run_length is None else math.ceil(n / run_length)
        bounds = [round(j * n / k) for j in range(k + 1)]
        runs.extend(tuple(members[bounds[j] : bounds[j + 1]]) for j in range(k))
    return runs


class StreamItem(NamedTuple):
    """One training sample of a stream run, as :class:`StreamRunSampler` yields it.

    Attributes:
        index: the data-set item.
        seed: the run's augmentation seed (every frame of a run draws the same geometric augmentation).
        start: the first frame of its run (becomes ``is_sequence_start``: stream state resets).
    """

    index: int
    seed: int
    start: bool


def _dist_defaults(num_replicas: int | None, rank: int | None) -> tuple[int, int]:
    live = dist.is_available() and dist.is_initialized()
    if num_replicas is None:
        num_replicas = dist.get_world_size() if live else 1
    if rank is None:
        rank = dist.get_rank() if live else 0
    return num_replicas, rank


class StreamRunSampler(DistributedSampler):
    """Training in streams: every batch slot of every rank plays its own runs of consecutive frames.

    The scenes are cut into runs (:func:`split_runs`); each epoch the runs are shuffled (``seed +
    epoch``, the same plan on every rank) and dealt to the ``num_replicas * batch_size`` slots,
    each run to the slot with the fewest frames so far. Slots shorter than the longest one keep
    drawing runs from the shuffled order (cyclically, the last one cut short), so every slot of
    every rank runs the same number of steps. Slot ``b`` of rank ``r`` is slot ``r * B + b``; the
    sampler interleaves the rank's slots, so a ``DataLoader`` with ``batch_size = B`` puts slot
    ``b``'s ``t``-th frame in row ``b`` of batch ``t``.

    It yields :class:`StreamItem` objects; :class:`StreamDataset` turns them into frames whose
    geometric augmentation is drawn once per run and whose ``is_sequence_start`` marks run starts.
    It subclasses ``DistributedSampler`` so Lightning leaves it in place (and calls :meth:`set_epoch`).

    Args:
        scenes: the data set's :class:`SceneIndex`.
        batch_size: slots per rank (the loader's batch size).
        run_length: frames per run (see :func:`split_runs`); None = whole scenes.
        num_replicas, rank: default the process group's, else 1 and 0.
        shuffle: shuffle the runs each epoch (else data-set order).
        seed: base seed of the shuffle and of the augmentation seeds.
    """

    def __init__(
        self,
        scenes: SceneIndex,
        batch_size: int = 1,
        run_length: int | None = None,
        num_replicas: int | None = None,
        rank: int | None = None,
        shuffle: bool = True,
        seed: int = 0,
    ) -> None:
        num_replicas, rank = _dist_defaults(num_replicas, rank)
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        runs = split_runs(scenes, run_length)
        if not runs:
            raise ValueError("a sequential sampler needs at least one scene")
        super().__init__(range(scenes.num_items), num_replicas=num_replicas, rank=rank, shuffle=shuffle, seed=seed)  # type: ignore[arg-type]
        self.scenes = scenes
        self.batch_size = batch_size
        self.run_length = run_length
        self.runs = runs

    def plan(self, epoch: int | None = None) -> list[list[list[StreamItem]]]:
        """``[rank][slot]`` -> the slot's items of ``epoch`` (default: the current one)."""
        epoch = self.epoch if epoch is None else epoch
        g = torch.Generator().manual_seed(self.seed + epoch)
        order = torch.randperm(len(self.runs), generator=g).tolist() if self.shuffle else list(range(len(self.runs)))
        slots = self.num_replicas * self.batch_size
        contents: list[list[StreamItem]] = [[] for _ in range(slots)]
        drawn = 0

        def deal(slot: int, run: tuple[int, ...]) -> None:
            nonlocal drawn
            seed = int(torch.randint(0, 1 << 62, (), generator=g))
            contents[slot].extend(StreamItem(i, seed, k == 0) for k, i in enumerate(run))
            drawn += 1

        for r in order:
            deal(min(range(slots), key=lambda s: (len(contents[s]), s)), self.runs[r])
        length = max(len(c) for c in contents)
        while any(len(c) < length for c in contents):
            for s in range(slots):
                if len(contents[s]) < length:
                    deal(s, self.runs[order[drawn % len(order)]])
        b = self.batch_size
        trimmed = [c[:length] for c in contents]
        return [trimmed[r * b : (r + 1) * b] for r in range(self.num_replicas)]

    def __iter__(self) -> Iterator[StreamItem]:  # type: ignore[override]
        slots = self.plan()[self.rank]
        for t in range(len(slots[0])):
            for slot in slots:
                yield slot[t]

    def __len__(self) -> int:
        return len(self.plan()[self.rank][0]) * self.batch_size


class SceneEvalSampler(DistributedSampler):
    """Evaluation in order: every frame exactly once, whole scenes per rank, no padding.

    The scenes (in data-set order) are cut into ``num_replicas`` contiguous groups of similar frame
    count (:func:`partition_scenes`); rank ``r`` deals its group to ``batch_size`` lanes (again
    contiguous, similar length) and plays them frame by frame, the longest lane first. It yields
    **batches** (lists of item indices): batch ``t`` holds the ``t``-th frame of every lane that
    still has one, so the batches shrink at the end of an epoch but row ``b`` is always lane ``b``.
    Use it with ``DataLoader(batch_size=None)`` (:meth:`~occplug.data.OccDataModule` does). Ranks
    may run different numbers of batches; occplug's evaluation runs no per-batch collective.

    Raises:
        ValueError: fewer scenes than ranks (a rank would have nothing to evaluate).
    """

    def __init__(
        self, scenes: SceneIndex, batch_size: int = 1, num_replicas: int | None = None, rank: int | None = None
    ) -> None:
        num_replicas, rank = _dist_defaults(num_replicas, rank)
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if len(scenes) < num_replicas:
            raise ValueError(
                f"sequential evaluation needs a scene per rank: {len(scenes)} scene(s) for {num_replicas} ranks"
            )
        super().__init__(range(scenes.num_items), num_replicas=num_replicas, rank=rank, shuffle=False)  # type: ignore[arg-type]
        self.scenes = scenes
        self.batch_size = batch_size

    def lanes(self, rank: int | None = None) -> list[list[int]]:
        """Rank ``rank``'s lanes (item indices in play order), longest first."""
        rank = self.rank if rank is None else rank
        lengths = [len(m) for m in self.scenes.items]
        mine = partition_scenes(lengths, self.num_replicas)[rank]
        groups = partition_scenes([lengths[s] for s in mine], self.batch_size)
        lanes = [[i for k in grp for i in self.scenes.items[mine[k]]] for grp in groups]
        return sorted((lane for lane in lanes if lane), key=len, reverse=True)

    def __iter__(self) -> Iterator[list[int]]:  # type: ignore[override]
        lanes = self.lanes()
        for t in range(len(lanes[0]) if lanes else 0):
            yield [lane[t] for lane in lanes if t < len(lane)]

    def __len__(self) -> int:
        lanes = self.lanes()
        return len(lanes[0]) if lanes else 0


class StreamDataset(Dataset[Frame]):
    """Wraps a data set for the stream samplers: a :class:`StreamItem` reads its item with the run's
    augmentation seed (:func:`occplug.data.augment.seeded_draws`) and marks run starts as
    ``is_sequence_start``; a list of indices (a :class:`SceneEvalSampler` batch) reads each item."""

    def __init__(self, base: Dataset[Frame]) -> None:
        self.base = base
        self.scenes = getattr(base, "scenes", None)

    def __len__(self) -> int:
        return len(self.base)  # type: ignore[arg-type]

    def __getitem__(self, key: Any) -> Any:
        if isinstance(key, StreamItem):
            from .augment import seeded_draws

            with seeded_draws(key.seed):
                frame = self.base[key.index]
            if key.start and not frame.extras.get("is_sequence_start", False):
                frame = copy.copy(frame)
                frame.extras = {**frame.extras, "is_sequence_start": True}
            return frame
        if isinstance(key, list):
            return [self.base[int(i)] for i in key]
        return self.base[key]


def stream_sampler(
    split: str,
    scenes: SceneIndex,
    batch_size: int,
    run_length: int | None = None,
    num_replicas: int | None = None,
    rank: int | None = None,
    seed: int = 0,
) -> DistributedSampler:
    """The sequential sampler of ``split``: :class:`StreamRunSampler` for ``train``, else :class:`SceneEvalSampler`."""
    if split == "train":
        return StreamRunSampler(
            scenes, batch_size, run_length=run_length, num_replicas=num_replicas, rank=rank, shuffle=True, seed=seed
        )
    return SceneEvalSampler(scenes, batch_size, num_replicas=num_replicas, rank=rank)
