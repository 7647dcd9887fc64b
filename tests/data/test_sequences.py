"""Scenes, adjacent frames and the stream samplers (training runs per slot, every evaluation frame exactly once)."""

from itertools import pairwise

import pytest
import torch

from occplug.data import collate_frames
from occplug.data.sequences import (
    SceneEvalSampler,
    SceneIndex,
    StreamDataset,
    StreamItem,
    StreamRunSampler,
    partition_scenes,
    relative_motion,
    split_runs,
)
from occplug.data.synthetic import SyntheticDataModule
from occplug.geometry import invert_pose, relative_pose


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
    assert [
        idx.neighbour(0, -1),
        idx.neighbour(0, 1),
        idx.neighbour(2, 1),
        idx.neighbour(3, -2),
        idx.neighbour(3, 5),
    ] == [0, 1, 2, 3, 4]
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
def test_eval_sampler_counts_every_frame_once_with_whole_scenes_per_rank(replicas, batch):
    idx = scenes([4, 3, 5, 2, 6, 3, 4])
    seen = []
    for rank in range(replicas):
        sampler = SceneEvalSampler(idx, batch_size=batch, num_replicas=replicas, rank=rank)
        batches = list(sampler)
        assert len(batches) == len(sampler)
        sizes = [len(bt) for bt in batches]
        assert sizes == sorted(sizes, reverse=True) and max(sizes) <= batch  # batches only shrink at the end
        lanes = sampler.lanes()
        for b, lane in enumerate(lanes):
            assert [bt[b] for bt in batches if len(bt) > b] == lane  # row b is always lane b
            assert idx.is_start(lane[0])
            for prev, cur in pairwise(lane):  # temporal order; a scene change lands on a first frame
                assert cur == idx.neighbour(prev, 1) and cur != prev or idx.is_start(cur)
        mine = sorted({idx.locate(i)[0] for bt in batches for i in bt})
        assert sum(len(idx.items[s]) for s in mine) == sum(sizes)  # whole scenes
        seen += [i for bt in batches for i in bt]
    assert sorted(seen) == list(range(idx.num_items))  # every frame exactly once over the ranks
    with pytest.raises(ValueError, match="a scene per rank"):
        SceneEvalSampler(scenes([3]), num_replicas=2, rank=0)


def test_split_runs_cuts_scenes_into_near_equal_runs():
    idx = scenes([5, 3, 1])
    assert split_runs(idx) == [(0, 1, 2, 3, 4), (5, 6, 7), (8,)]
    assert split_runs(idx, 2) == [(0, 1), (2,), (3, 4), (5, 6), (7,), (8,)]  # 5 -> 2+1+2, 3 -> 2+1
    assert split_runs(idx, 3) == [(0, 1), (2, 3, 4), (5, 6, 7), (8,)]
    with pytest.raises(ValueError, match="run_length"):
        split_runs(idx, 0)


@pytest.mark.parametrize(("replicas", "batch", "run_length"), [(1, 1, None), (1, 3, 2), (2, 2, 3), (3, 1, None)])
def test_training_slots_each_play_their_own_runs(replicas, batch, run_length):
    idx = scenes([4, 3, 5, 2, 6, 3, 4])
    runs = set(split_runs(idx, run_length))
    samplers = [
        StreamRunSampler(idx, batch, run_length, num_replicas=replicas, rank=r, seed=3) for r in range(replicas)
    ]
    plans = [s.plan() for s in samplers]
    assert all(p == plans[0] for p in plans)  # every rank computes the same plan
    lengths = {len(slot) for rank in plans[0] for slot in rank}
    assert len(lengths) == 1  # equal steps on every slot of every rank
    covered = set()
    for rank, sampler in enumerate(samplers):
        items = list(sampler)
        assert len(items) == len(sampler)
        for b in range(batch):
            slot = items[b::batch]
            assert slot == plans[0][rank][b]
            # cut the slot at run starts: each piece is a prefix of one run, with one augmentation seed
            pieces, cur = [], []
            for item in slot:
                if item.start and cur:
                    pieces.append(cur)
                    cur = []
                cur.append(item)
            pieces.append(cur)
            assert slot[0].start
            for piece in pieces:
                indices = tuple(i.index for i in piece)
                assert any(run[: len(indices)] == indices for run in runs)
                assert len({i.seed for i in piece}) == 1
                covered.add(indices)
    assert runs <= covered  # every run is played in the epoch
    first = samplers[0].plan(0)
    samplers[0].set_epoch(1)
    assert samplers[0].plan() != first  # reshuffled per epoch


def test_stream_dataset_marks_run_starts_and_draws_the_bev_augmentation_once_per_run():
    aug = {"bev": {"flip_x": 0.5, "flip_y": 0.5, "rotate": [-30, 30], "scale": [0.8, 1.2]}}
    dm = SyntheticDataModule(preset="tiny", train_scenes=1, sequential=True, augment=aug)
    plain = SyntheticDataModule(preset="tiny", train_scenes=1).dataset("train")
    data = StreamDataset(dm.dataset("train"))
    run = [StreamItem(0, 11, True), StreamItem(1, 11, False), StreamItem(2, 11, False)]
    frames = [data[item] for item in run]
    assert [f.extras["is_sequence_start"] for f in frames] == [True, False, False]
    assert data[StreamItem(1, 11, True)].extras["is_sequence_start"]  # a run may start mid-scene
    a = frames[0].extras["bev_aug"]
    assert all(torch.equal(f.extras["bev_aug"], a) for f in frames)
    assert not torch.allclose(a, torch.eye(4, dtype=torch.float64))
    for k in (0, 1):
        rel_aug = relative_pose(frames[k].ego_to_global.double(), frames[k + 1].ego_to_global.double())
        rel = relative_pose(plain[k].ego_to_global.double(), plain[k + 1].ego_to_global.double())
        # the augmented motion is the true motion seen in the augmented ego frames: A T A^-1, rigid
        torch.testing.assert_close(rel_aug, a @ rel @ torch.linalg.inv(a), rtol=0, atol=1e-5)
        torch.testing.assert_close(
            rel_aug[:3, :3] @ rel_aug[:3, :3].T, torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-6
        )
    other = data[StreamItem(1, 12, False)].extras["bev_aug"]
    assert not torch.equal(other, a)  # another run draws another transform


def test_sequential_loaders_train_in_runs_and_evaluate_every_frame_once():
    dm = SyntheticDataModule(preset="tiny", train_scenes=2, val_scenes=3, sequential={"run_length": 2}, batch_size=2)
    val = list(dm.val_dataloader())
    assert [len(b) for b in val] == [2, 2, 1, 1]  # 3 scenes of 2 frames on 2 lanes: 4 + 2 frames
    tokens = [t for b in val for t in b.token]
    assert len(tokens) == len(set(tokens)) == 6
    assert [b.is_sequence_start.tolist() for b in val] == [[True, True], [False, False], [True], [False]]
    train = list(dm.train_dataloader())
    assert all(len(b) == 2 for b in train)
    for b in range(2):
        slot = [(bt.scene[b], int(bt.frame_index[b]), bool(bt.is_sequence_start[b])) for bt in train]
        for (s0, f0, _), (s1, f1, start) in pairwise(slot):
            assert start or (s1 == s0 and f1 == f0 + 1)
    assert dm.stream_run_length == 2
    with pytest.raises(ValueError, match="data.sequential.run_lenght"):
        SyntheticDataModule(preset="tiny", sequential={"run_lenght": 2})


def test_sequential_synthetic_loader_flags_sequence_starts_and_relative_motion():
    dm = SyntheticDataModule(
        preset="tiny", train_scenes=1, val_scenes=1, sequential=True, batch_size=1, adjacent_offsets=[-1, 1]
    )
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
