"""Scenes, adjacent frames and the sequential sampler (whole contiguous scenes per rank, lanes per batch slot)."""

import pytest
import torch

from occplug.data import collate_frames
from occplug.data.sequences import SceneIndex, SceneSequenceSampler, partition_scenes, relative_motion
from occplug.data.synthetic import SyntheticDataModule
from occplug.geometry import invert_pose


def scenes(lengths):
    names, items, k = [], [], 0
    for s, n in enumerate(lengths):
        names.append(f"s{s}")
        items.append(tuple(range(k, k + n)))
        k += n
    return SceneIndex(tuple(names), tuple(items))


def test_scene_index_neighbours_clamp_at_scene_ends():
    idx = SceneIndex.from_scene_names(["a", "a", "a", "b", "b"])
    assert idx.items == ((0, 1, 2), (3, 4))
    assert [idx.neighbour(0, -1), idx.neighbour(0, 1), idx.neighbour(2, 1), idx.neighbour(3, -2), idx.neighbour(3, 5)] == [0, 1, 2, 3, 4]
    assert [idx.is_start(i) for i in range(5)] == [True, False, False, True, False]
    with pytest.raises(ValueError, match="two scenes"):
        SceneIndex(("a", "b"), ((0, 1), (1, 2)))


def test_partition_is_contiguous_balanced_and_never_empty_when_possible():
    groups = partition_scenes([10, 10, 10, 10, 40], 2)
    assert groups == [[0, 1, 2, 3], [4]]
    groups = partition_scenes([5, 5, 5], 3)
    assert groups == [[0], [1], [2]]
    assert partition_scenes([5, 5], 4) == [[0], [1], [], []]
    for parts in (1, 2, 3, 4):
        g = partition_scenes([3, 7, 2, 9, 4, 4], parts)
        assert [i for grp in g for i in grp] == list(range(6)) and all(g)


@pytest.mark.parametrize(("replicas", "batch"), [(1, 1), (1, 2), (2, 1), (2, 2), (3, 2)])
def test_sampler_gives_each_rank_whole_contiguous_scenes_in_order(replicas, batch):
    idx = scenes([4, 3, 5, 2, 6, 3, 4])
    per_rank = []
    lengths = set()
    for rank in range(replicas):
        sampler = SceneSequenceSampler(idx, batch_size=batch, num_replicas=replicas, rank=rank)
        order = list(sampler)
        assert len(order) == len(sampler)
        lengths.add(len(order))
        lanes = [order[b::batch] for b in range(batch)]
        for lane in lanes:
            # every lane plays frames in temporal order; a scene change always lands on a scene's first frame
            for prev, cur in zip(lane, lane[1:]):
                assert cur == idx.neighbour(prev, 1) and cur != prev or idx.is_start(cur)
            assert idx.is_start(lane[0])
        per_rank.append(sampler.lanes()[rank])
    assert len(lengths) == 1  # DDP: every rank runs the same number of steps
    # without padding, the ranks' own scenes are contiguous blocks covering every scene once
    own = []
    for rank_lanes in per_rank:
        for lane in rank_lanes:
            seen = []
            for i in lane:
                s = idx.locate(i)[0]
                if idx.is_start(i) and s in seen:
                    break  # padding replays from here
                if not seen or seen[-1] != s:
                    seen.append(s)
            own.append(seen)
    flat = [s for lane in own for s in lane]
    assert sorted(flat) == list(range(len(idx))) and flat == sorted(flat)


def test_sampler_shuffles_scene_order_per_epoch_but_keeps_frames_in_order():
    idx = scenes([3] * 6)
    sampler = SceneSequenceSampler(idx, shuffle=True, seed=1, num_replicas=1, rank=0)
    first = list(sampler)
    sampler.set_epoch(1)
    second = list(sampler)
    assert sorted(first) == sorted(second) == list(range(18)) and first != second
    for order in (first, second):
        starts = order[::3]
        assert all(idx.is_start(i) for i in starts)
        assert all(order[k + 1] == order[k] + 1 for k in range(18) if k % 3 != 2)


def test_sequential_synthetic_loader_flags_sequence_starts_and_relative_motion():
    dm = SyntheticDataModule(preset="tiny", train_scenes=1, val_scenes=1, sequential=True, batch_size=1,
                             adjacent_offsets=[-1, 1])
    batches = list(dm.val_dataloader())
    assert [b.frame_index.tolist() for b in batches] == [[0], [1]]
    assert [b.is_sequence_start.tolist() for b in batches] == [[True], [False]]
    frame = dm.dataset("val")[1]
    motion = relative_motion(frame, -1)
    expected = invert_pose(frame.ego_to_global) @ frame.adjacent[-1].ego_to_global
    assert torch.allclose(motion, expected) and motion.dtype == torch.float64
    assert collate_frames([frame]).adjacent[-1].frame_index.tolist() == [0]
    with pytest.raises(KeyError, match="no adjacent frame"):
        relative_motion(frame, 2)
