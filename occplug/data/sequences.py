"""Sequences: scenes in temporal order, adjacent frames, and a sampler that streams whole scenes.

Every occplug data set is a list of frames in **scene-major temporal order**: the items of one
scene are contiguous or at least ordered by time, and :class:`SceneIndex` records which items
form each scene. On top of that this module gives every reader the same two things:

* **Adjacent frames** (:meth:`SceneIndex.neighbour`): a sample can carry the frames ``k`` steps
  before or after it in its scene (``Frame.adjacent[k]``). Offsets are **clamped** at the scene's
  ends, as the synthetic world does: ``adjacent[-1]`` of a scene's first frame is that frame itself
  (its token, timestamp and pose say so). :func:`relative_motion` gives the ego motion between a
  frame and one of its adjacent frames.
* **A sequential sampler** (:class:`SceneSequenceSampler`): each epoch yields every scene in
  temporal order so that stream state can be carried from one batch to the next. With batch size
  ``B`` a rank's scenes are dealt to ``B`` *lanes*; batch slot ``b`` always continues lane ``b``.
  Under DDP every rank gets whole, contiguous scenes. ``Frame.extras["is_sequence_start"]`` (set by
  the readers: the frame is the first of its scene in the data set) becomes
  ``Batch.is_sequence_start``: reset the stream state of that slot.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch import Tensor
from torch.utils.data import DistributedSampler

from occplug.geometry import relative_pose

from .frame import Frame

__all__ = ["SceneIndex", "SceneSequenceSampler", "partition_scenes", "relative_motion"]


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
        return cls(tuple(names), tuple(tuple(range(s * frames_per_scene, (s + 1) * frames_per_scene)) for s in range(len(names))))

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


class SceneSequenceSampler(DistributedSampler):
    """Yields every scene in temporal order, dealt to ``batch_size`` lanes per rank.

    The scenes (in data-set order, or shuffled per epoch with ``shuffle``) are cut into
    ``num_replicas * batch_size`` contiguous groups of similar frame count (:func:`partition_scenes`);
    rank ``r`` owns groups ``r * B .. r * B + B - 1`` (whole, contiguous scenes) and lane ``b`` of
    the rank plays group ``r * B + b`` frame by frame. The sampler interleaves the lanes, so a
    ``DataLoader`` with ``batch_size = B`` puts lane ``b``'s ``t``-th frame in slot ``b`` of batch
    ``t``.

    Every lane of every rank is padded to the same length (ranks must run the same number of
    steps under DDP) by replaying its own scenes from their first frame; a lane with no scene of its
    own (fewer scenes than lanes) replays the scenes from the start. Padding always restarts at a
    scene's first frame, so ``is_sequence_start`` stays right; padded frames are seen twice in that
    epoch (as with ``DistributedSampler``). Evaluate with one lane on one device to see every frame
    exactly once.

    It subclasses ``DistributedSampler`` so Lightning leaves it in place instead of injecting its
    own; :meth:`set_epoch` reshuffles the scene order when ``shuffle`` is on.

    Args:
        scenes: the data set's :class:`SceneIndex`.
        batch_size: lanes per rank (the loader's batch size).
        num_replicas: ranks; default the initialised process group's size, else 1.
        rank: this rank; default the process group's rank, else 0.
        shuffle: permute the scene order each epoch (frames inside a scene keep their order).
        seed: base seed of that permutation (``seed + epoch``).
    """

    def __init__(self, scenes: SceneIndex, batch_size: int = 1, num_replicas: int | None = None,
                 rank: int | None = None, shuffle: bool = False, seed: int = 0) -> None:
        if num_replicas is None:
            num_replicas = dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1
        if rank is None:
            rank = dist.get_rank() if dist.is_available() and dist.is_initialized() else 0
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if len(scenes) == 0:
            raise ValueError("a sequential sampler needs at least one scene")
        super().__init__(range(scenes.num_items), num_replicas=num_replicas, rank=rank, shuffle=shuffle, seed=seed)  # type: ignore[arg-type]
        self.scenes = scenes
        self.batch_size = batch_size

    def lanes(self, epoch: int | None = None) -> list[list[list[int]]]:
        """``[rank][lane]`` -> item indices, padded (see the class docstring)."""
        epoch = self.epoch if epoch is None else epoch
        order = list(range(len(self.scenes)))
        if self.shuffle:
            g = torch.Generator().manual_seed(self.seed + epoch)
            order = torch.randperm(len(order), generator=g).tolist()
        groups = partition_scenes([len(self.scenes.items[s]) for s in order], self.num_replicas * self.batch_size)
        contents = [[i for k in grp for i in self.scenes.items[order[k]]] for grp in groups]
        everything = [i for s in order for i in self.scenes.items[s]]
        length = max(len(c) for c in contents)
        padded = []
        for c in contents:
            source = c or everything
            reps = math.ceil(length / len(source))
            padded.append((source * reps)[:length])
        b = self.batch_size
        return [padded[r * b:(r + 1) * b] for r in range(self.num_replicas)]

    def __iter__(self) -> Iterator[int]:  # type: ignore[override]
        lanes = self.lanes()[self.rank]
        for t in range(len(lanes[0])):
            for lane in lanes:
                yield lane[t]

    def __len__(self) -> int:
        return len(self.lanes()[self.rank][0]) * self.batch_size
